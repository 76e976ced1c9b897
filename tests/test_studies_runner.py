"""Runner: seeds independent of jobs / Dask, metrics.json keys as DESIGN.md says, outputs written atomically.

The study model here is a small stand-in defined in this file (the real one composes INS, maps, matchers and
fusers): truth flies east along a parallel; the free-inertial error is a per-run random ramp, the aided estimator
a bounded random error with a covariance and fixes.
"""

from __future__ import annotations

import json
from dataclasses import dataclass

import numpy as np
import pytest

from magnav_ins.core.errors import ConfigError
from magnav_ins.core.frames import meters_to_latlon
from magnav_ins.core.units import DEG_TO_RAD
from magnav_ins.studies import runner
from magnav_ins.studies.runner import EstimatorOutput, RunOutput

DESIGN_KEYS = {
    "matcher",
    "fusion",
    "rms_horizontal_m",
    "mean_horizontal_m",
    "max_horizontal_m",
    "final_horizontal_m",
    "divergence_rate",
    "availability",
    "nees_mean",
}
EXTRA_KEYS = {
    "fix_attempts", "fixes_issued", "non_finite_fraction", "no_fix_reasons", "fix_nees_mean", "hpl_median_m",
    "hpl_exceedance", "rms_after_first_fix_m", "nees_divergence_rate",
}  # fmt: skip
#: the stand-in's protection level: sqrt(2 ln 10) sigma, exceeded by a circular Gaussian error 10 % of the time
HPL_K10 = float(np.sqrt(2.0 * np.log(10.0)))


@dataclass(frozen=True)
class StandInModel:
    name: str = "standin"
    n: int = 200
    sigma_aided_m: float = 5.0
    fail_at_run: int = -1
    availability: float = 0.8

    def estimator_names(self) -> tuple[str, ...]:
        return ("aided", "free_inertial")

    def run(self, seed: np.random.SeedSequence) -> RunOutput:
        rng = np.random.default_rng(seed)
        if seed.spawn_key and seed.spawn_key[-1] == self.fail_at_run:
            raise RuntimeError("stand-in failure")
        t = np.arange(self.n, dtype=float)
        lat = np.full(self.n, -35.0 * DEG_TO_RAD)
        lon = (149.0 + 1e-4 * t) * DEG_TO_RAD

        def offset(dn, de):
            dlat, dlon = meters_to_latlon(dn, de, lat)
            return lat + dlat, lon + dlon

        slope = rng.normal(0.0, 1.0, 2)
        fl, fo = offset(slope[0] * t, slope[1] * t)
        s = self.sigma_aided_m
        an, ae = rng.normal(0, s, self.n), rng.normal(0, s, self.n)
        al, ao = offset(an, ae)
        cov = np.broadcast_to(np.diag([s**2, s**2]), (self.n, 2, 2)).copy()
        fix_t = t[::10]
        avail = rng.random(len(fix_t)) < self.availability
        # two kinds of "no fix", with numbers in them that must not split the count
        reasons = tuple(
            "" if ok else (f"flat map: variability {0.01 * k:.2f} < 0.3" if k % 2 else f"ambiguous peak: ratio 1.{k}")
            for k, ok in enumerate(avail)
        )
        fn, fe = rng.normal(0, 2.0, len(fix_t)), rng.normal(0, 2.0, len(fix_t))
        fdlat, fdlon = meters_to_latlon(fn, fe, lat[::10])
        fix_lat = np.where(avail, lat[::10] + fdlat, np.nan)
        fix_lon = np.where(avail, lon[::10] + fdlon, np.nan)
        fix_cov = np.broadcast_to(np.diag([4.0, 4.0]), (len(fix_t), 2, 2)).copy()
        return RunOutput(
            t,
            lat,
            lon,
            (
                EstimatorOutput(
                    "aided",
                    "ml",
                    "ukf",
                    al,
                    ao,
                    cov,
                    fix_t,
                    fix_lat,
                    fix_lon,
                    fix_cov,
                    avail,
                    reasons,
                    hpl_m=np.full(self.n, HPL_K10 * s),
                ),  # fmt: skip
                EstimatorOutput("free_inertial", None, "free_inertial", fl, fo),
            ),
        )


def _strip(doc):
    return {k: v for k, v in doc.items() if k != "wall_s"}


def test_metrics_json_keys_and_values(tmp_path):
    doc = runner.run_study(StandInModel(), runs=4, seed=7, out_dir=tmp_path)
    on_disk = json.loads((tmp_path / "metrics.json").read_text())
    assert _strip(on_disk) == _strip(doc)
    assert set(on_disk) == {"name", "estimators", "free_inertial", "runs", "seed", "wall_s", "warnings"}
    assert on_disk["warnings"] == []
    assert on_disk["runs"] == 4 and on_disk["seed"] == 7
    assert set(on_disk["estimators"]) == {"aided"}
    aided = on_disk["estimators"]["aided"]
    # DESIGN.md's keys plus the documented extras (metrics.py docstring), nothing else
    expected = DESIGN_KEYS | {"fix_error_bins", "fix_within_3m_fraction"} | EXTRA_KEYS
    assert set(aided) == expected
    assert set(on_disk["free_inertial"]) == expected
    assert set(aided["fix_error_bins"]) == {"lt_3m", "3_to_10m", "10_to_20m", "ge_20m"}
    assert aided["matcher"] == "ml" and aided["fusion"] == "ukf"
    # stand-in: 2-D Gaussian error with sigma 5 m per axis -> E[e^2] = 50 m^2, NEES mean 2, no divergence
    assert aided["rms_horizontal_m"] == pytest.approx(np.sqrt(50.0), rel=0.06)
    assert aided["nees_mean"] == pytest.approx(2.0, rel=0.1)
    assert aided["divergence_rate"] == 0.0
    # availability ~ 0.8 by construction; fix errors Rayleigh(sigma=2): P(e < 3) = 1 - exp(-9/8) = 0.675
    assert aided["availability"] == pytest.approx(0.8, abs=0.1)
    assert aided["fix_within_3m_fraction"] == pytest.approx(1 - np.exp(-9 / 8), abs=0.1)
    # fix errors N(0, 2^2) per axis with covariance diag(4, 4): fix NEES 2; HPL exceeded at 10 % of the samples
    assert aided["fix_nees_mean"] == pytest.approx(2.0, rel=0.25)
    assert aided["hpl_median_m"] == pytest.approx(HPL_K10 * 5.0) and aided["hpl_exceedance"] == pytest.approx(
        0.1, abs=0.03
    )
    assert on_disk["free_inertial"]["hpl_median_m"] is None and on_disk["free_inertial"]["hpl_exceedance"] is None
    # a ramp drifts without bound: the baseline "diverges" in every run
    assert on_disk["free_inertial"]["divergence_rate"] == 1.0
    for f in ("runs.nc", "report.md", "track.png", "error_vs_time.png", "error_cdf.png", "free_inertial.png"):
        assert (tmp_path / f).stat().st_size > 0, f
    assert not list(tmp_path.glob(".*part"))


def test_no_fix_reasons_counted_and_warned(tmp_path):
    doc = runner.run_study(StandInModel(), runs=3, seed=2)
    m = doc["estimators"]["aided"]
    reasons = m["no_fix_reasons"]
    # every "no fix" is counted once, under its reason without the numbers
    assert set(reasons) <= {"flat map", "ambiguous peak"}
    assert sum(reasons.values()) == m["fix_attempts"] - m["fixes_issued"] > 0
    assert doc["warnings"] == []
    # no fix at all: the study says so, with the reasons, in metrics.json and report.md
    doc = runner.run_study(StandInModel(availability=0.0), runs=2, seed=2, out_dir=tmp_path, plots=False)
    m = doc["estimators"]["aided"]
    assert m["fixes_issued"] == 0 and m["availability"] == 0.0
    assert sum(m["no_fix_reasons"].values()) == m["fix_attempts"] == 40
    [line] = doc["warnings"]
    assert f"0 of {m['fix_attempts']} fix attempts gave a fix" in line and "flat map x" in line
    assert "ambiguous peak x" in line
    assert line in (tmp_path / "report.md").read_text()
    assert json.loads((tmp_path / "metrics.json").read_text())["warnings"] == [line]


def test_seeds_independent_of_jobs():
    m = StandInModel()
    d1 = runner.run_study(m, runs=5, seed=3, jobs=1)
    d2 = runner.run_study(m, runs=5, seed=3, jobs=2)
    assert _strip(d1) == _strip(d2)
    d3 = runner.run_study(m, runs=5, seed=4, jobs=1)
    assert _strip(d3) != _strip(d1)


def test_chunked_runs_same_as_single_runs():
    """Handing a worker several consecutive runs at once (the suite's runs of one case) changes nothing but where
    they run: every run in order, with its own seed; a chunk that does not divide the runs is cut short."""
    m = StandInModel()
    one = runner.execute(m, 5, 3, jobs=1)
    for chunk in (2, 5, 7):
        got = runner.execute(m, 5, 3, jobs=2, chunk=chunk)
        assert [s.index for s in got] == [0, 1, 2, 3, 4]
        for a, b in zip(one, got, strict=True):
            assert np.array_equal(a.t, b.t) and np.array_equal(a.lat_true, b.lat_true)
            for name in a.estimators:
                assert np.array_equal(a.estimators[name].err_n, b.estimators[name].err_n)
    with pytest.raises(ConfigError, match="chunk"):
        runner.execute(m, 5, 3, jobs=2, chunk=0)


def test_seeds_independent_of_dask_cluster():
    distributed = pytest.importorskip("dask.distributed")
    m = StandInModel()
    d1 = runner.run_study(m, runs=4, seed=11, jobs=1)
    with (
        distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=None) as cl,
        distributed.Client(cl) as client,
    ):
        d2 = runner.run_study(m, runs=4, seed=11, scheduler=client)
        d3 = runner.run_study(m, runs=4, seed=11, scheduler=cl.scheduler_address)
    assert _strip(d1) == _strip(d2) == _strip(d3)


def test_failed_run_writes_nothing(tmp_path):
    with pytest.raises(RuntimeError, match="stand-in failure"):
        runner.run_study(StandInModel(fail_at_run=2), runs=4, seed=1, out_dir=tmp_path / "out")
    assert not (tmp_path / "out").exists() or not any((tmp_path / "out").iterdir())


def test_runs_nc_round_trip(tmp_path):
    import xarray as xr

    runner.run_study(StandInModel(), runs=3, seed=5, out_dir=tmp_path, plots=False)
    ds = xr.load_dataset(tmp_path / "runs.nc")
    assert ds["err_north_m"].dtype == np.float32
    assert ds.sizes["run"] == 3 and list(ds["estimator"].values) == ["aided", "free_inertial"]
    # the stored errors reproduce the metrics
    doc = json.loads((tmp_path / "metrics.json").read_text())
    e = np.hypot(ds["err_north_m"].values[:, 0].astype(float), ds["err_east_m"].values[:, 0].astype(float))
    assert np.sqrt(np.mean(e**2)) == pytest.approx(doc["estimators"]["aided"]["rms_horizontal_m"], rel=1e-5)
    hpl = ds["hpl_m"].values[:, 0].astype(float)
    assert ds["hpl_m"].attrs["units"] == "m" and np.isnan(ds["hpl_m"].values[:, 1]).all()
    assert np.mean(e > hpl) == pytest.approx(doc["estimators"]["aided"]["hpl_exceedance"], abs=1e-9)


def test_plot_error_leaves_no_outputs(tmp_path, monkeypatch):
    from magnav_ins.studies import plots

    def boom(*a, **k):
        raise RuntimeError("plot failed")

    monkeypatch.setattr(plots, "plot_error_cdf", boom)
    with pytest.raises(RuntimeError, match="plot failed"):
        runner.run_study(StandInModel(), runs=2, seed=1, out_dir=tmp_path)
    assert list(tmp_path.iterdir()) == []
