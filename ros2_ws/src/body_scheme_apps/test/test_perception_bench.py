"""Tests of the perception benchmark's corner-noise study (the rendered part is the tracker's tests' business)."""

import math

from body_scheme_apps.perception_bench import CAMERAS, STUDY_DISTANCES, STUDY_TARGETS, corner_noise_study


def test_the_study_reports_every_cell_and_a_plate_beats_a_tag_along_the_ray():
    figures = corner_noise_study(trials=20, seed=1)
    names = ("lateral_mm", "depth_mm", "depth_p90_mm", "rot_deg", "flip_rate")
    expected = {f"perception_{c}_{t}_{d:g}m_{n}" for c in CAMERAS for t in STUDY_TARGETS for d in STUDY_DISTANCES
                for n in names}
    assert set(figures) == expected and all(math.isfinite(v) for v in figures.values())
    for camera in CAMERAS:
        tag, plate = (f"perception_{camera}_{target}_2m" for target in ("tag", "plate"))
        assert figures[plate + "_depth_mm"] < figures[tag + "_depth_mm"]
        assert figures[tag + "_depth_mm"] > 3.0 * figures[tag + "_lateral_mm"]  # a monocular camera's depth
        assert figures[tag + "_depth_mm"] > figures[f"perception_{camera}_tag_1m_depth_mm"]
