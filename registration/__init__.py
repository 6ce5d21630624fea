"""Registration of one pair of clouds: the method registry, the solvers, the baselines and :func:`register`.

Every method is a callable ``method(src, tgt, src_normals=None, tgt_normals=None)`` on numpy
clouds returning a :class:`MethodResult` (see :mod:`linereg.registration.methods`). Importing this
package registers them all in :data:`METHODS`: the solvers ``robust`` (the default of
:func:`register`), ``adam_loss`` and ``svd_irls`` (:mod:`linereg.registration.solvers`), and the
classical baselines ``icp_point``, ``icp_plane``, ``fgr`` and ``fricp``
(:mod:`linereg.registration.baselines`). :func:`register` (also ``linereg.register``) runs any of
them, or a trained network, on arrays, tensors, Open3D clouds or files.
"""

from linereg.registration import baselines, solvers
from linereg.registration.api import LearnedRegistration, RegistrationResult, register
from linereg.registration.methods import METHODS, Method, MethodResult, run_centered

__all__ = [
    "METHODS",
    "LearnedRegistration",
    "Method",
    "MethodResult",
    "RegistrationResult",
    "baselines",
    "register",
    "run_centered",
    "solvers",
]
