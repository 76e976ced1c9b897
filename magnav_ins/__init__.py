"""magnav_ins: a strapdown INS aided by geophysical (magnetic / gravity) map matching.

Conventions, written once (see also ``core``):

* Units: SI in every signature (m, s, rad, m/s^2, rad/s). Noise densities are root-PSD
  (rad/s/sqrt(Hz), m/s^2/sqrt(Hz)). Field values are in the unit of their kind (nT, mGal).
  Degrees appear only at the edges (files, CLI, MAVLink).
* Frames: navigation frame ``n`` = local NED; body frame ``b`` = FRD; geodesy on WGS-84,
  heights ellipsoidal. Names carry frames: ``v_n`` (velocity in n), ``f_b`` (specific force in b),
  ``omega_ib_b`` (angular rate of b w.r.t. inertial, resolved in b), ``C_nb`` (matrix that projects
  b-frame vectors into n: ``x_n = C_nb @ x_b``).
* Attitude: quaternions are scalar-last ``[x, y, z, w]`` (as ``scipy.spatial.transform.Rotation``);
  ``q_nb`` rotates body vectors into nav. Only ``aiding/fusion/graph.py`` sees GTSAM's order.
* Time: float seconds on one clock, named ``t``; matched with ``searchsorted`` and a tolerance.
* Randomness: every random component takes a ``numpy.random.Generator``.
* Threads: the package's linear algebra is on small matrices (15x15 filters, 30x30 Van Loan exponentials), where a
  multi-threaded BLAS only adds overhead (measured: scipy ``expm`` of a 30x30 matrix 0.1 ms single-threaded, 30 ms
  with OpenBLAS threads on a busy 2-core machine). Importing ``magnav_ins`` before numpy therefore defaults
  ``OPENBLAS_NUM_THREADS`` and ``MKL_NUM_THREADS`` to 1 (set them yourself to override); parallelism comes from
  processes (``--jobs``) and numba kernels instead.
"""

import os as _os

for _var in ("OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    _os.environ.setdefault(_var, "1")

__version__ = "0.1.0"
