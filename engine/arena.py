"""The arena every scene lives in, defined once: a square of `ARENA_METRES` on a side, walled on four sides, drawn
at `PIXELS_PER_METRE` on Kinetix's `SCREEN_PIXELS`-pixel square screen (its `screen_dim` and `pixels_per_unit`).

Plain numbers with no imports, so that configs, the physics, the level tools, the renderers and the studio can all
take them from here."""

ARENA_METRES = 5.0
"""Side of the arena in metres; its walls stand on the square's edges."""
PIXELS_PER_METRE = 100
"""Pixels per metre at full resolution (Kinetix's `pixels_per_unit`)."""
SCREEN_PIXELS = 500
"""Side of the full-resolution screen in pixels (Kinetix's `screen_dim`): the arena at `PIXELS_PER_METRE`."""
