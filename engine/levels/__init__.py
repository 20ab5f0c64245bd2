"""Levels: reading and writing Kinetix's JSON level files (more to come: random levels and mutations, issue 4)."""
