"""A dataclass that is also a JAX pytree, without depending on flax (the engine imports only jax and numpy)."""

from __future__ import annotations

import dataclasses
from typing import TypeVar

import jax

T = TypeVar("T")


def pytree_dataclass(cls: type[T]) -> type[T]:
    """Freeze `cls` as a dataclass whose fields are all pytree leaves, with a `replace` method."""
    cls = dataclasses.dataclass(frozen=True)(cls)
    cls.replace = dataclasses.replace  # type: ignore[attr-defined]
    return jax.tree_util.register_dataclass(cls)
