"""Where to fly the SITL square: rank 2 km squares over the bridge's map by how much the map says on their
weakest leg (the RMS along-leg gradient of ``builtin:osborne-magnetic``, nT/km, on a 10 m step), so that map fixes
come on every leg, not only on two. Prints the best homes (north first, clockwise, as ``bench/sitl_flight.py
--orientation ne`` flies them) and the default home's figures.

``python bench/sitl_route.py [--side-m 2000] [--top 8]``
"""

from __future__ import annotations

import argparse
import math

import numpy as np

from magnav_ins.core.frames import meters_to_latlon
from magnav_ins.maps.builtin import load_map


def leg_gradient_nt_per_km(fmap, lat: float, lon: float, dn: float, de: float, step_m: float = 10.0) -> float:  # noqa: ANN001
    """RMS gradient (nT/km) of the map along the straight leg from (``lat``, ``lon``) rad by ``dn``, ``de`` m;
    -1 when any of it is off the map."""
    n = int(math.hypot(dn, de) / step_m) + 1
    s = np.linspace(0.0, 1.0, n)
    dla, dlo = meters_to_latlon(dn * s, de * s, lat, 0.0)
    v = np.asarray(fmap.value(lat + dla, lon + dlo), float).ravel()
    if not np.all(np.isfinite(v)):
        return -1.0
    return float(np.sqrt(np.mean((np.diff(v) / step_m) ** 2)) * 1000.0)


def square_legs(fmap, lat: float, lon: float, side_m: float) -> list[float]:  # noqa: ANN001
    dla, dlo = meters_to_latlon(side_m, side_m, lat, 0.0)
    return [
        leg_gradient_nt_per_km(fmap, lat, lon, side_m, 0.0),
        leg_gradient_nt_per_km(fmap, lat + dla, lon, 0.0, side_m),
        leg_gradient_nt_per_km(fmap, lat + dla, lon + dlo, -side_m, 0.0),
        leg_gradient_nt_per_km(fmap, lat, lon + dlo, 0.0, -side_m),
    ]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--side-m", type=float, default=2000.0)
    ap.add_argument("--top", type=int, default=8)
    ap.add_argument("--n", type=int, default=40, help="candidate homes per axis")
    args = ap.parse_args()
    fmap = load_map("builtin:osborne-magnetic")
    la0, la1, lo0, lo1 = fmap.bounds_latlon
    pad_la, pad_lo = meters_to_latlon(args.side_m + 500.0, args.side_m + 500.0, 0.5 * (la0 + la1), 0.0)
    rows = []
    for lat in np.linspace(la0 + 0.005, la1 - float(pad_la), args.n):
        for lon in np.linspace(lo0 + 0.005, lo1 - float(pad_lo), args.n):
            legs = square_legs(fmap, float(lat), float(lon), args.side_m)
            if min(legs) > 0:
                rows.append((min(legs), math.degrees(lat), math.degrees(lon), legs))
    rows.sort(reverse=True)
    print("weakest leg nT/km  home (--home=LAT,LON)  legs N, E, S, W")
    for r in rows[: args.top]:
        print(f"{r[0]:8.0f}  {r[1]:.4f},{r[2]:.4f}  {[round(x) for x in r[3]]}")
    d = square_legs(fmap, math.radians(-21.94), math.radians(140.76), args.side_m)
    print(f"default home -21.94,140.76: {[round(x) for x in d]}")


if __name__ == "__main__":
    main()
