"""linereg: unsupervised rigid point-cloud registration with the line-intersection loss.

The core modules (``linereg.se3``, ``linereg.procrustes``, ``linereg.knn``, ``linereg.pointcloud``,
``linereg.metrics``, ``linereg.io``, ...) hold the geometry shared by every layer; the
subpackages ``linereg.losses``, ``linereg.models``, ``linereg.datasets``,
``linereg.registration`` and ``linereg.train`` build on them. :func:`register` aligns two
clouds and :func:`register_scans` many (imported on first use, so ``import linereg`` does not load torch).

Conventions, stated once for the whole project:

* column vectors; a rigid transform maps source to target, ``tgt ≈ R @ src + t``;
  4x4 matrices are named ``T_tgt_src``;
* angles in radians inside the library, degrees only in reported metrics (``err_r_deg``);
* a twist ``xi`` in se(3) is ordered ``(omega, v)``: rotation first, then translation;
* batched tensors are ``(B, N, 3)``; functions also accept any leading batch dimensions
  where documented.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

__version__ = "0.1.0"
__all__ = ["MultiwayOptions", "RegistrationResult", "__version__", "register", "register_many", "register_scans"]

# In a source checkout the subpackages live in top-level folders (losses/, models/, ...) next to
# this one; the wheel maps them into linereg/. Make them importable as linereg.<name> from the
# checkout too, without putting the top-level names on sys.path as packages of their own.
_CHECKOUT = Path(__file__).resolve().parent.parent
if not (Path(__file__).resolve().parent / "losses").is_dir() and (_CHECKOUT / "losses" / "__init__.py").is_file():
    __path__.append(str(_CHECKOUT))

_LAZY = {
    "register": "linereg.registration.api",
    "register_many": "linereg.registration.many",
    "register_scans": "linereg.registration.multiway",
    "MultiwayOptions": "linereg.registration.multiway",
    "RegistrationResult": "linereg.registration.api",
}


def __getattr__(name: str) -> Any:
    if name in _LAZY:
        import importlib

        return getattr(importlib.import_module(_LAZY[name]), name)
    raise AttributeError(f"module 'linereg' has no attribute {name!r}")
