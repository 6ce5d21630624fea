"""linereg core: geometry shared by every layer (SE(3) maths, Procrustes, kNN/FPS, metrics, I/O).

Conventions, stated once for the whole project:

* column vectors; a rigid transform maps source to target, ``tgt ≈ R @ src + t``;
  4x4 matrices are named ``T_tgt_src``;
* angles in radians inside the library, degrees only in reported metrics (``err_r_deg``);
* a twist ``xi`` in se(3) is ordered ``(omega, v)``: rotation first, then translation;
* batched tensors are ``(B, N, 3)``; functions also accept any leading batch dimensions
  where documented.
"""

__version__ = "0.1.0"
