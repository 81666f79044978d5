"""Smoke runs of the baseline studies (`--quick`), skipped by default (`-m slow`)."""

import importlib.util
import json
from pathlib import Path

import pytest

EXPERIMENTS = Path(__file__).resolve().parents[2] / "experiments"


def _load(name):
    spec = importlib.util.spec_from_file_location(name, EXPERIMENTS / f"{name}.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


@pytest.mark.slow
def test_bandwidth_study_quick(tmp_path):
    results = _load("bandwidth").main(["--quick", "--out", str(tmp_path)])
    data = json.loads((tmp_path / "bandwidth_quick.json").read_text())
    assert (tmp_path / "bandwidth_quick_fig11.png").stat().st_size > 0
    cc = results["colorchecker"]
    # On the ColorChecker the events beat the bandwidth-matched frame camera.
    assert cc["ours"]["sam_deg"] < cc["matched"]["sam_deg"]
    assert data["setup"]["bits_per_event"] == 16


@pytest.mark.slow
def test_event_rate_study_quick(tmp_path):
    rows = _load("event_rate").main(["--quick", "--out", str(tmp_path)])
    by = {(r["baseline_rel"], r["threshold"]): r["events_per_pixel"] for r in rows}
    # Lower constant light and a lower threshold both give more events (paper Fig. 12).
    assert by[(0.01, 0.15)] > by[(0.1, 0.15)]
    assert by[(0.03, 0.15)] > by[(0.03, 0.3)]
    assert all(r["max_sweeps_s"] <= 30.0 for r in rows)


@pytest.mark.slow
def test_cassi_study_quick(tmp_path):
    rows = _load("cassi_compare").main(["--quick", "--out", str(tmp_path)])
    assert {r["method"] for r in rows} == {"ours", "GAP-TV", "DeSCI"}
    assert (tmp_path / "cassi_compare_quick.json").is_file()
