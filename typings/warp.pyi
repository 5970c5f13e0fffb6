"""Warp as mypy sees it here: untyped (every name Any).

Warp's own stubs type vectors (wp.vec3d) as Python classes, while the @wp.func and @wp.kernel
bodies in kernels/ are Warp's kernel language, compiled by Warp, whose arithmetic and builtins
(wp.dot on a vec3d) those stubs do not follow; mypy would report that code, which Warp accepts."""
from typing import Any

def __getattr__(name: str) -> Any: ...
