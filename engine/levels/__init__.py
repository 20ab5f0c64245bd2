"""Levels: the `Level` pytree (a scene plus roles, densities and action bindings), Kinetix's JSON level files
(`kinetix_json`), random levels sampled on the device in the style of Kinetix's generator (`generator`:
`sample_random_level`, `sample_random_levels`) and ACCEL's level edits (`mutations`: `mutate_level`,
`mutate_levels`, `apply_edit`)."""
