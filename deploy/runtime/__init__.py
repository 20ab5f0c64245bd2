"""What the `impulse` commands share: the one run loop every long-running process runs in (`runloop`, `progress`),
the supervisor and live status display of `impulse launch`, the checks made before anything starts (`preflight`),
run directories (`run_dirs`), logging, GPU selection (`devices`), the compilation cache and the wiring of monitoring
into the services."""
