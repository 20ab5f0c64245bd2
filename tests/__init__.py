"""The test suite: it mirrors the rooms (tests/engine/physics, tests/bus, ...); shared helpers are in tests.support."""
