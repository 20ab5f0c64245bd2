"""Throughput and learning benchmarks, run as `impulse bench NAME`. Each prints JSON lines (with the JAX version,
backend and device) and states every speed as a ratio against the reference system measured in the same run on
the same machine, since figures from another machine or day cannot be compared."""
