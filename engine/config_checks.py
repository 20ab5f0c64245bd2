"""Checks every room's configuration sections share: a number in its range, a list of device positions. Errors
name the full dotted key (`ppo.num_envs`), which `deploy.config` shows as it is. In the engine, the bottom room,
so that every section (the engine's own included) can use them."""

from __future__ import annotations


def check_range(
    name: str,
    value: float,
    *,
    at_least: float | None = None,
    above: float | None = None,
    at_most: float | None = None,
    below: float | None = None,
) -> None:
    """Refuse a number outside its range with a ValueError naming `name`, the full dotted key ("ppo.num_envs"):
    `at_least`/`at_most` are inclusive bounds, `above`/`below` exclusive ones (give at most one of each pair).
    NaN is never in range."""
    low, low_open = (above, True) if above is not None else (at_least, False)
    high, high_open = (below, True) if below is not None else (at_most, False)
    fits_low = low is None or (value > low if low_open else value >= low)
    fits_high = high is None or (value < high if high_open else value <= high)
    if fits_low and fits_high:
        return
    if low is not None and high is not None:
        rule = f"in {'(' if low_open else '['}{low}, {high}{')' if high_open else ']'}"
    elif low is not None:
        rule = f"{'>' if low_open else '>='} {low}"
    else:
        rule = f"{'<' if high_open else '<='} {high}"
    raise ValueError(f"{name} must be {rule}, got {value}")


def check_device_list(name: str, devices: tuple[int, ...]) -> None:
    """Device positions are distinct non-negative integers."""
    if any(isinstance(d, bool) or not isinstance(d, int) or d < 0 for d in devices) or len(set(devices)) != len(
            devices):
        raise ValueError(f"{name} must list distinct device numbers >= 0, got {list(devices)}")
