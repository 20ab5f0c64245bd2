"""How Impulse is run; it may import every room, and nothing imports it except the console entry point (and the
benchmarks), so the rooms stay usable as libraries.

- `cli.py`: the `impulse` command line; `config.py`: typed configuration loading (defaults, a TOML file,
  `key=value` overrides); `run_config.py`: the run configuration composing every room's section.
- `commands/`: one thin module per `impulse` command (parse, call, exit code).
- `runtime/`: what the commands share: the one run loop every long-running process runs in, the supervisor and
  live status display of `impulse launch`, the checks before anything starts, run directories, logging, GPU
  selection, the compilation cache, monitoring wiring.
- `cluster/`: runs beyond one machine: the SLURM template, the container recipe, the trial certificate script
  (`impulse router` itself is a command).
"""
