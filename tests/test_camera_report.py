"""The scan's colour camera report (gscan.scanning.camera.camera_report) and its line in the summary and `info`
(gscan.cli.output.camera_line): "kept" only when the check kept the focal length and the depth's edges do not
contradict it; otherwise a warning that names why and every frame resting on it, never "checked"."""
from __future__ import annotations

import math

import pytest

from gscan.cli.output import camera_line
from gscan.io.camera import Intrinsics
from gscan.scanning.calibration import CORRECTED, KEPT, UNCONFIRMED, FocalCheck
from gscan.scanning.camera import camera_report
from gscan.scanning.depth_edges import EdgeEvidence

K = Intrinsics(585.0, 585.0, 320.0, 240.0, 640, 480)
FRAMES = [f"{i:06d}" for i in range(5)]


def focal(verdict: str, estimate: float, low: float, high: float) -> FocalCheck:
    corrected = verdict == CORRECTED
    return FocalCheck(estimate if corrected else 1.0, {0.9: 0.8, 1.0: 0.7}, 16, 12, 0.01, corrected, 0.8,
                      estimate=estimate, low=low, high=high, verdict=verdict,
                      reason=None if verdict != UNCONFIRMED else "a reason")


def edges(verdict: str) -> EdgeEvidence:
    return EdgeEvidence(verdict, (), 8 if verdict == "not registered" else 0, 0.004, 22.0, 0.9)


def test_kept_with_edges_that_agree_is_kept():
    r = camera_report(focal(KEPT, 1.0, 0.98, 1.02), edges("registered"), K, FRAMES)
    assert r["verdict"] == KEPT and r["confirmed"] and r["warning"] is None and r["unconfirmed_frames"] == [], r
    assert r["interval_px"] == [pytest.approx(573.3), pytest.approx(596.7)], r
    assert "checked, kept" in camera_line(r)[1]


def test_kept_but_depth_edges_off_the_colour_cannot_be_confirmed():
    """The texture would keep 585 px, the depth's jumps lie 22 px off the colour edges: could not confirm, with the
    flags that fix it, and every frame flagged."""
    r = camera_report(focal(KEPT, 1.0, 0.98, 1.02), edges("not registered"), K, FRAMES)
    assert r["verdict"] == UNCONFIRMED and not r["confirmed"] and r["unconfirmed_frames"] == FRAMES, r
    assert "--depth-intrinsics" in r["reason"] and "--depth-to-color" in r["depth_edges"]["fix"], r
    tag, text = camera_line(r)
    assert "could not confirm" in text and "checked" not in text and "warning" in tag[0], text


def test_unconfirmed_says_why_and_flags_every_frame():
    r = camera_report(focal(UNCONFIRMED, 0.9, -math.inf, 0.95), edges("undecided"), K, FRAMES)
    assert r["interval_px"][0] is None and r["interval_px"][1] == pytest.approx(555.8), r
    assert r["colour_focal_px"][0] == 585.0 and not r["corrected"] and r["unconfirmed_frames"] == FRAMES, r
    assert "could not confirm the focal length 585 px (a reason)" in r["warning"], r
    assert "all 5 frames" in r["warning"] and "--depth-intrinsics" in r["warning"], r


def test_corrected_reports_its_interval():
    r = camera_report(focal(CORRECTED, 0.9, 0.88, 0.92), edges("not registered"), K, FRAMES)
    assert r["verdict"] == CORRECTED and r["confirmed"] and r["colour_focal_px"][0] == 526.5, r
    assert r["unconfirmed_frames"] == [] and "514.8-538.2 px" in camera_line(r)[1], r
