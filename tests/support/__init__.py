"""Helpers shared by the tests: scenes, level samples, damaged checkpoints, launched processes and their statuses.
Imported as `tests.support.<module>`; a few also run as scripts (bus_procs, sharded_update_check)."""
