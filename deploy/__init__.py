"""How Impulse is run: the `impulse` command line, typed configuration loading (TOML files plus `key=value`
overrides), logging setup, the run loop every long-running process shares, and `impulse launch` (the local
multi-process supervisor with its live status display), `impulse router` for runs across machines, GPU
selection, and the job-scheduler and container templates (`deploy/slurm`, `deploy/container`). It may import
every room; nothing imports it except the console entry point, so the rooms stay usable as libraries."""
