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
"""

__version__ = "0.1.0"
