"""How Impulse is run: the `impulse` command line, typed configuration loading (TOML files plus `key=value`
overrides), logging setup, and later the local multi-process launcher with its live status, router and
multi-host configuration, and job-scheduler templates. It may import every room; nothing imports it except the
console entry point, so the rooms stay usable as libraries."""
