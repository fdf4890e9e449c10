"""The printable marker sheet: true scale, every id readable by our tracker, plates as one piece, a PDF of A4
pages."""

import re

import cv2
import numpy as np
import pytest

from body_scheme_core.errors import InvalidInputError
from body_scheme_core.perception import MarkerTracker
from body_scheme_core.plates import plates_from_markers
from body_scheme_core.transforms import transform_from_xyz_rpy
from body_scheme_core.world import Marker
from body_scheme_sim.markers import aruco_dictionary
from body_scheme_sim.sheet import marker_pixels, sheet_pages, write_sheet

DPI = 150
DISTANCE = 1.0  # m: the page is seen frontally from here by a camera whose pixel is one printed dot


def _markers():
    return [Marker(id=k, link=f"link{k}", size=0.04 if k % 2 else 0.06) for k in range(10)]


def test_the_sheet_round_trips_through_our_tracker_at_true_scale():
    """10 ids of two sizes: rendered as pages, seen by a camera whose pixel is one dot at 1 m, every marker is
    detected with its id, and its pose puts it 1 m away (within 0.5 %): the printed square has the planned size."""
    markers = _markers()
    pages, boxes = sheet_pages(markers, dpi=DPI)
    f = DISTANCE * DPI / 0.0254
    poses = {}
    for page in pages:
        K = [[f, 0.0, page.shape[1] / 2 - 0.5], [0.0, f, page.shape[0] / 2 - 0.5], [0.0, 0.0, 1.0]]
        tracker = MarkerTracker(K, marker_sizes={m.id: m.size for m in markers}, max_ambiguity=1.0)
        found, rejected = tracker.detect(page)
        assert rejected == [] and not set(found) & set(poses)
        poses.update(found)
    assert sorted(poses) == [m.id for m in markers]
    for marker_id, T in poses.items():
        assert T[2, 3] == pytest.approx(DISTANCE, rel=5e-3), marker_id
    for _, marker_id, _, square in boxes:
        assert square == marker_pixels(markers[marker_id].size, DPI)


def test_a_wrong_size_in_the_tracker_shows_as_a_wrong_distance():
    """The check above can fail: told the 40 mm markers are 44 mm, the tracker puts them 10 % farther."""
    markers = _markers()
    pages, boxes = sheet_pages(markers, dpi=DPI)
    page = pages[next(k for k, marker_id, _, _ in boxes if marker_id == 1)]  # a 40 mm marker's page
    f = DISTANCE * DPI / 0.0254
    K = [[f, 0.0, page.shape[1] / 2 - 0.5], [0.0, f, page.shape[0] / 2 - 0.5], [0.0, 0.0, 1.0]]
    tracker = MarkerTracker(K, marker_sizes={m.id: m.size * 1.1 for m in markers}, max_ambiguity=1.0)
    poses, _ = tracker.detect(page)
    assert poses[1][2, 3] == pytest.approx(1.1 * DISTANCE, rel=5e-3)


def test_the_pdf_has_a4_pages_and_the_png_its_resolution(tmp_path):
    """write_sheet writes a PDF whose pages are A4 (595 x 842 pt) and a PNG with the dpi recorded; many markers
    take several pages."""
    from PIL import Image

    paths = write_sheet(_markers(), tmp_path / "markers", dpi=DPI)
    assert [p.name for p in paths] == ["markers.pdf", "markers-1.png", "markers-2.png"]
    media = re.findall(rb"/MediaBox \[ ?0 0 ([\d.]+) ([\d.]+) ?\]", paths[0].read_bytes())
    assert media and all(abs(float(w) - 595.3) < 1 and abs(float(h) - 841.9) < 1 for w, h in media)
    assert Image.open(paths[1]).info["dpi"] == pytest.approx((DPI, DPI), abs=0.05)  # PNG stores dots per metre
    many = [Marker(id=k, link="l", size=0.08) for k in range(40)]
    assert len(write_sheet(many, tmp_path / "many", dpi=DPI)) > 3
    assert [p.name for p in write_sheet(many[:1], tmp_path / "one", dpi=DPI)] == ["one.pdf", "one.png"]


def test_markers_that_cannot_be_printed_are_refused():
    """A marker too small to print at the resolution, or wider than the page, is a clear error."""
    with pytest.raises(InvalidInputError, match="too small"):
        sheet_pages([Marker(id=1, link="l", size=0.001)], dpi=DPI)
    with pytest.raises(InvalidInputError, match="does not fit"):
        sheet_pages([Marker(id=1, link="l", size=0.5)], dpi=DPI)
    with pytest.raises(InvalidInputError, match="dpi"):
        sheet_pages(_markers(), dpi=10)


def _plate(ids, size=0.03, pitch=0.04, rotated=False):
    """A 2 x 2 grid plate of tags on ``tool`` (tag frames as in a grid board), the first id the plate's."""
    markers = []
    for k, tag_id in enumerate(ids):
        link2marker = np.eye(4)
        link2marker[:3, 3] = ((k % 2) * pitch, -(k // 2) * pitch, 0.02)
        if rotated and k == 3:  # a cube's face: turned 90 deg out of the plate
            link2marker[:3, :3] = transform_from_xyz_rpy((0, 0, 0), (np.pi / 2, 0, 0))[:3, :3]
        markers.append(Marker(id=tag_id, link="tool", size=size, link2marker=link2marker, plate=ids[0]))
    return markers


def test_a_flat_plate_is_printed_as_one_piece_with_the_spacing_the_tracker_assumes():
    """A 2 x 2 plate beside single markers: its tags on one piece, each tag's centre on the printed page relative
    to the plate's reference tag as in the marker file (within a dot), and the tracker, told the plate, gives one
    pose for it, 1 m away, with no tag refused."""
    markers = [*_markers()[:3], *_plate([20, 21, 22, 23])]
    pages, boxes = sheet_pages(markers, dpi=DPI)
    on_page = {marker_id: page for page, marker_id, _, _ in boxes}
    assert len({on_page[k] for k in (20, 21, 22, 23)}) == 1
    page = pages[on_page[20]]
    f = DISTANCE * DPI / 0.0254
    K = [[f, 0.0, page.shape[1] / 2 - 0.5], [0.0, f, page.shape[0] / 2 - 0.5], [0.0, 0.0, 1.0]]
    corners, ids, _ = cv2.aruco.ArucoDetector(aruco_dictionary()).detectMarkers(page)
    centre = {int(i): c.reshape(4, 2).mean(axis=0) for i, c in zip(np.ravel(ids), corners, strict=True)}
    dots = DPI / 0.0254
    by_id = {m.id: m for m in markers}
    for tag_id in (21, 22, 23):
        planned = (np.linalg.inv(by_id[20].link2marker) @ by_id[tag_id].link2marker)[:2, 3] * dots
        printed = (centre[tag_id] - centre[20]) * (1.0, -1.0)  # image rows grow down, the tag's y points up
        assert np.abs(printed - planned).max() < 1.0, (tag_id, printed, planned)  # within a dot (0.17 mm)
    sizes = {m.id: m.size for m in markers}
    poses, rejected = MarkerTracker(K, marker_sizes=sizes, max_ambiguity=1.0,
                                    plates=plates_from_markers(markers)).detect(page)
    assert 20 in poses and not {21, 22, 23} & set(poses) and rejected == []
    assert poses[20][2, 3] == pytest.approx(DISTANCE, rel=5e-3)


def test_a_plate_that_is_not_flat_is_printed_tag_by_tag_and_overlapping_tags_are_refused():
    pages, boxes = sheet_pages(_plate([20, 21, 22, 23], rotated=True), dpi=DPI)
    assert sorted(marker_id for _, marker_id, _, _ in boxes) == [20, 21, 22, 23]
    with pytest.raises(InvalidInputError, match="overlaps"):
        sheet_pages(_plate([20, 21, 22, 23], pitch=0.02), dpi=DPI)
