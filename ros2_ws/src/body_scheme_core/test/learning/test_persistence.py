"""Tests of saving and loading the learner's state file."""

import json
import os

import numpy as np
import pytest

from body_scheme_core import __version__
from body_scheme_core.errors import ModelFileError
from body_scheme_core.learning.learner import BodySchemeLearner
from body_scheme_core.learning.persistence import (
    STATE_FILE_VERSION,
    STATE_FORMAT,
    encode_state,
    load_state,
    save_state,
    write_state_text,
)
from body_scheme_core.world import make_session, planar_2dof


@pytest.fixture(scope="module")
def trained():
    """A learner past bootstrapping on the 2-DOF robot, and its session."""
    robot = planar_2dof()
    session = make_session(robot, 80, seed=0, visibility=0.9)
    learner = BodySchemeLearner(robot.marker_ids, robot.n_actions)
    for t in range(60):
        learner.update(session.actions[t], session.observations[t], stamp=0.1 * t)
    return learner, session


def _document(learner, tmp_path):
    path = tmp_path / "state.json"
    save_state(learner, path)
    return path, json.loads(path.read_text())


def test_round_trip_through_a_file_continues_identically(trained, tmp_path):
    """save -> load gives a learner that produces the same events and predictions as the original."""
    learner, session = trained
    path = tmp_path / "state.json"
    save_state(learner, path)
    a_copy = BodySchemeLearner.from_state(json.loads(json.dumps(learner.to_state())))
    loaded = load_state(path)
    assert loaded.step == learner.step == 60 and loaded.last_stamp == pytest.approx(5.9)
    for t in range(60, 80):
        events = [e.to_dict() for e in a_copy.update(session.actions[t], session.observations[t])]
        assert [e.to_dict() for e in loaded.update(session.actions[t], session.observations[t])] == events
        p, q = a_copy.predict(session.actions[t]), loaded.predict(session.actions[t])
        assert all(np.array_equal(p[i], q[i]) for i in p)


def test_file_layout(trained, tmp_path):
    """The document carries format tag, version, core version, time stamp and the state."""
    learner, _ = trained
    _, doc = _document(learner, tmp_path)
    assert doc["format"] == STATE_FORMAT == "body_scheme_state"
    assert doc["version"] == STATE_FILE_VERSION == 1
    assert doc["core_version"] == __version__
    assert "T" in doc["saved_at"] and doc["saved_at"].endswith("+00:00")
    assert doc["state"]["step"] == 60


def test_atomic_write_replaces_and_leaves_no_temporary_files(trained, tmp_path):
    """An existing file is replaced and no temporary file stays behind."""
    learner, _ = trained
    path = tmp_path / "state.json"
    path.write_text("old content")
    assert save_state(learner, path) == os.path.abspath(path)
    assert json.loads(path.read_text())["format"] == STATE_FORMAT
    assert sorted(os.listdir(tmp_path)) == ["state.json"]


def test_failed_write_keeps_the_old_file(trained, tmp_path, monkeypatch):
    """If writing fails midway the old file is untouched and the temporary file is removed."""
    learner, _ = trained
    path = tmp_path / "state.json"
    path.write_text("old content")

    def broken(*args, **kwargs):
        raise OSError("disk full")

    monkeypatch.setattr(os, "fsync", broken)
    with pytest.raises(OSError, match="disk full"):
        save_state(learner, path)
    assert path.read_text() == "old content"
    assert sorted(os.listdir(tmp_path)) == ["state.json"]


def test_missing_file(tmp_path):
    """A missing file is a ModelFileError naming the path."""
    with pytest.raises(ModelFileError, match="does not exist"):
        load_state(tmp_path / "nope.json")


def test_truncated_and_corrupt_json(trained, tmp_path):
    """Truncated, empty and non-JSON files are ModelFileErrors, never crashes."""
    learner, _ = trained
    path, _ = _document(learner, tmp_path)
    text = path.read_text()
    path.write_text(text[: len(text) // 2])
    with pytest.raises(ModelFileError, match="not valid JSON"):
        load_state(path)
    path.write_text("")
    with pytest.raises(ModelFileError, match="empty"):
        load_state(path)
    path.write_bytes(b"\x80\x04\x95 pickle, not json")
    with pytest.raises(ModelFileError):
        load_state(path)
    path.write_text("[1, 2, 3]")
    with pytest.raises(ModelFileError, match="JSON object"):
        load_state(path)


def test_wrong_format_tag_and_newer_version(trained, tmp_path):
    """Other formats and newer versions are refused with a clear message."""
    learner, _ = trained
    path, doc = _document(learner, tmp_path)
    path.write_text(json.dumps(dict(doc, format="something_else")))
    with pytest.raises(ModelFileError, match="not a body scheme state file"):
        load_state(path)
    path.write_text(json.dumps(dict(doc, version=STATE_FILE_VERSION + 1)))
    with pytest.raises(ModelFileError, match="newer"):
        load_state(path)
    path.write_text(json.dumps(dict(doc, version="1")))
    with pytest.raises(ModelFileError, match="invalid version"):
        load_state(path)


def test_missing_keys(trained, tmp_path):
    """A document or state without a required key is a ModelFileError naming it."""
    learner, _ = trained
    path, doc = _document(learner, tmp_path)
    path.write_text(json.dumps({k: v for k, v in doc.items() if k != "state"}))
    with pytest.raises(ModelFileError, match="no 'state'"):
        load_state(path)
    for key in ["entries", "monitor", "gp_batch", "rigid_batch", "calibration", "history", "config"]:
        state = {k: v for k, v in doc["state"].items() if k != key}
        path.write_text(json.dumps(dict(doc, state=state)))
        with pytest.raises(ModelFileError, match=key):
            load_state(path)


def test_wrong_array_shapes(trained, tmp_path):
    """Arrays of the wrong shape anywhere in the state are refused."""
    learner, _ = trained
    path, doc = _document(learner, tmp_path)
    bad = json.loads(json.dumps(doc))
    bad["state"]["history"][0]["actions"] = [0.0, 0.0, 0.0]
    path.write_text(json.dumps(bad))
    with pytest.raises(ModelFileError, match="history actions must have shape"):
        load_state(path)
    bad = json.loads(json.dumps(doc))
    bad["state"]["monitor"]["errors"] = bad["state"]["monitor"]["errors"][:-1]
    path.write_text(json.dumps(bad))
    with pytest.raises(ModelFileError, match="errors"):
        load_state(path)
    bad = json.loads(json.dumps(doc))
    bad["state"]["root_samples"][0]["actions"] = [1.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0]
    path.write_text(json.dumps(bad))
    with pytest.raises(ModelFileError, match="root sample actions"):
        load_state(path)


def test_nan_in_arrays(trained, tmp_path):
    """NaN or Infinity anywhere in the file is refused (they are not JSON)."""
    learner, _ = trained
    path, doc = _document(learner, tmp_path)
    bad = json.loads(json.dumps(doc))
    bad["state"]["history"][-1]["actions"][0] = float("nan")
    path.write_text(json.dumps(bad))  # Python writes the non-standard token NaN
    with pytest.raises(ModelFileError, match="NaN"):
        load_state(path)
    bad["state"]["history"][-1]["actions"][0] = float("inf")
    path.write_text(json.dumps(bad))
    with pytest.raises(ModelFileError, match="NaN or infinite"):
        load_state(path)


def test_inconsistent_state_is_refused(trained, tmp_path):
    """A tree that refers to unknown models, or a model of an unknown part, is a ModelFileError."""
    learner, _ = trained
    path, doc = _document(learner, tmp_path)
    bad = json.loads(json.dumps(doc))
    bad["state"]["tree"] = [12345]
    path.write_text(json.dumps(bad))
    with pytest.raises(ModelFileError, match="unknown model"):
        load_state(path)
    bad = json.loads(json.dumps(doc))
    bad["state"]["entries"][0]["parent"] = 77
    path.write_text(json.dumps(bad))
    with pytest.raises(ModelFileError, match="unknown part"):
        load_state(path)


def test_infinite_action_limits_round_trip(tmp_path):
    """Continuous joints (infinite limits) survive a save and load although JSON has no infinity."""
    learner = BodySchemeLearner([1, 2], 2, action_lower=[-np.inf, -1.0], action_upper=[np.inf, 1.0])
    path = tmp_path / "state.json"
    save_state(learner, path)
    loaded = load_state(path)
    np.testing.assert_array_equal(loaded.action_lower, [-np.inf, -1.0])
    np.testing.assert_array_equal(loaded.action_upper, [np.inf, 1.0])


def test_numbers_that_overflow_are_refused_at_load_and_non_finite_state_at_save(trained, tmp_path):
    """``1e999`` (infinity by overflow, valid JSON syntax) is refused when loading; a learner holding a non-finite
    value cannot be saved (ModelFileError, not a raw ValueError), and nothing is written."""
    learner, _ = trained
    path, doc = _document(learner, tmp_path)
    doc["state"]["history"][0]["actions"][0] = 12345.5
    path.write_text(json.dumps(doc).replace("12345.5", "1e999"))
    with pytest.raises(ModelFileError, match="not finite"):
        load_state(path)
    broken = load_state(_document(learner, tmp_path)[0])  # a copy: the fixture is shared
    broken.state.history[0][1][0] = float("inf")
    with pytest.raises(ModelFileError, match="NaN or infinite"):
        save_state(broken, tmp_path / "other.json")
    assert not (tmp_path / "other.json").exists()


def test_encoding_then_writing_is_saving(trained, tmp_path):
    """A node encodes under its learner lock and writes after: the file is the one save_state writes."""
    learner, _ = trained
    save_state(learner, tmp_path / "saved.json")
    written = write_state_text(encode_state(learner), tmp_path / "written.json")
    assert written == str(tmp_path / "written.json")
    saved, encoded = (json.loads((tmp_path / name).read_text()) for name in ("saved.json", "written.json"))
    assert {k: v for k, v in saved.items() if k != "saved_at"} == {k: v for k, v in encoded.items() if k != "saved_at"}
    assert load_state(written).step == learner.step


def test_huge_integers_and_deep_nesting_are_model_file_errors(trained, tmp_path):
    """A 5000-digit integer (Python refuses to convert it: a ValueError before issue 20) or a number nested 100,000
    lists deep is refused as a ModelFileError, anywhere in the file."""
    learner, _ = trained
    path, _ = _document(learner, tmp_path)
    text = path.read_text()
    for mutated in (text.replace('"step":', '"step":' + "7" * 5000 + ',"was":', 1),
                    text.replace('"version":1', '"version":' + "1" * 30, 1),
                    text.replace('"step":', '"step":' + "[" * 100_000 + "]" * 100_000 + ',"was":', 1)):
        path.write_text(mutated)
        with pytest.raises(ModelFileError):
            load_state(path)
