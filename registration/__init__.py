"""Registration of one pair of clouds: the method registry, the solvers, the baselines and :func:`register`.

Every method is a callable ``method(src, tgt, src_normals=None, tgt_normals=None)`` on numpy
clouds returning a :class:`MethodResult` (see :mod:`linereg.registration.methods`). The default of
:func:`register` (also ``linereg.register``), ``robust`` (:mod:`linereg.registration.robust`), is
numpy and scipy only, in one module per stage: pose sets (:mod:`~linereg.registration.poses`),
the coarse CD-W stage (:mod:`~linereg.registration.coarse`), the Welsch polish
(:mod:`~linereg.registration.welsch`), the pose search (:mod:`~linereg.registration.search`), the
plane-to-plane steps (:mod:`~linereg.registration.planes`) and their settings
(:mod:`~linereg.registration.robust_options`). The torch solvers ``adam_loss`` and ``svd_irls``
(:mod:`linereg.registration.solvers`) and the classical baselines ``icp_point``, ``icp_plane``,
``fgr`` and ``fricp`` (:mod:`linereg.registration.baselines`) register in :data:`METHODS` when
first needed (a name not yet registered, or a listing), so that importing this package does not
import torch. :func:`register` runs any of them, or a trained network, on arrays, tensors,
Open3D clouds or files, applies an initial guess (:func:`run_with_init`) and scores every result
alike (:func:`~linereg.registration.evaluation.assess_registration`); :func:`register_many`
(:mod:`~linereg.registration.many`) registers many pairs and :func:`register_scans`
(:mod:`~linereg.registration.multiway`) places many scans in one frame through a pose graph, both
imported on first use (one pair's registration does not need them).
"""

from typing import Any

from linereg.registration import robust
from linereg.registration.api import RegistrationResult, register
from linereg.registration.learned import LearnedRegistration
from linereg.registration.methods import METHODS, Method, MethodResult, run_centered, run_with_init

__all__ = [
    "METHODS",
    "LearnedRegistration",
    "Method",
    "MethodResult",
    "MultiwayOptions",
    "MultiwayResult",
    "RegistrationResult",
    "baselines",
    "register",
    "register_many",
    "register_scans",
    "robust",
    "run_centered",
    "run_with_init",
    "solvers",
]


_LAZY = {
    "register_many": "many",
    "register_scans": "multiway",
    "MultiwayOptions": "multiway",
    "MultiwayResult": "multiway",
}
"""Members imported on first use, and their modules: what one pair's registration does not need."""


def __getattr__(name: str) -> Any:
    """The torch-based modules and :data:`_LAZY`'s members, imported on first use."""
    import importlib

    if name in ("solvers", "baselines"):
        return importlib.import_module(f"linereg.registration.{name}")
    if name in _LAZY:
        return getattr(importlib.import_module(f"linereg.registration.{_LAZY[name]}"), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
