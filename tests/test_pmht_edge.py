"""The search-gate edge rule of PMHT (``edge_check``, off by default; module docstring "Search gate")."""

from __future__ import annotations

import numpy as np

from magnav_ins.aiding.matchers._batch import edge_normals, truncated_sides


def _grid(centre: tuple[float, float], cov: np.ndarray, h: float = 1000.0, m: int = 41):
    on = np.linspace(-h, h, m)
    N, E = np.meshgrid(on, on, indexing="ij")
    d = np.stack([N - centre[0], E - centre[1]], -1)
    ll = -0.5 * np.einsum("...i,ij,...j->...", d, np.linalg.inv(cov), d)
    return ll, int(np.argmax(ll))


def test_edge_normals_name_the_borders_the_peak_region_crosses():
    """A compact peak in the middle touches no border; one at the south border touches the south one only; a
    ridge along east touches the west and east borders."""
    ll, k = _grid((0.0, 0.0), np.diag([100.0**2, 100.0**2]))
    assert edge_normals(ll, k).shape == (0, 2)
    ll, k = _grid((-1000.0, 0.0), np.diag([100.0**2, 100.0**2]))
    assert edge_normals(ll, k).tolist() == [[-1.0, 0.0]]
    ll, k = _grid((0.0, 0.0), np.diag([100.0**2, 1e5**2]))
    assert sorted(edge_normals(ll, k).tolist()) == [[0.0, -1.0], [0.0, 1.0]]


def test_truncated_sides_spare_a_ridge_along_the_border_normal_but_not_a_tilted_narrow_direction():
    """Through the east border: a fix that knows north only (the along-track ridge) is not truncated; a compact fix
    is; a long ridge tilted 20 degrees off east whose narrow direction crosses the south border is truncated there
    although its marginal north variance is far above the gate's half-width (the information, not the marginal)."""
    half = np.array([1000.0, 1000.0])
    east, south = np.array([[0.0, 1.0]]), np.array([[-1.0, 0.0]])
    assert truncated_sides(east, np.diag([100.0**2, 1e5**2]), half).shape == (0, 2)
    assert truncated_sides(east, np.diag([100.0**2, 300.0**2]), half).tolist() == [[0.0, 1.0]]
    a = np.radians(20.0)
    u, v = np.array([np.sin(a), np.cos(a)]), np.array([np.cos(a), -np.sin(a)])  # long axis, narrow axis
    cov = 3e4**2 * np.outer(u, u) + 300.0**2 * np.outer(v, v)
    assert np.sqrt(cov[0, 0]) > 5 * half[0]
    assert truncated_sides(south, cov, half).tolist() == [[-1.0, 0.0]]
