"""The shipped sample bags: bags/README.md and `make bags` regenerate them, message for message."""

from __future__ import annotations

import json
import pathlib
import re
import shlex

import numpy as np
import pytest

from body_scheme_apps import record
from body_scheme_nodes.bag_io import SESSION_TOPICS, read_messages

pytestmark = pytest.mark.slow  # make test-fast leaves it out (docs/architecture.md, Tests)

REPO = pathlib.Path(__file__).resolve().parents[4]
BAGS = REPO / "bags"



# ---------------------------------------------------------------------- the shipped sample bags
def _readme_commands():
    """``{bag name: argv}`` of the regenerate commands in bags/README.md."""
    commands = {}
    for line in (BAGS / "README.md").read_text().splitlines():
        if line.startswith("python -m body_scheme_apps.record "):
            argv = shlex.split(line)[3:]
            commands[pathlib.Path(argv[argv.index("--out") + 1]).name] = argv
    return commands


def _assert_same(a, b, where):
    """Decoded rclpy messages (fields, arrays, sequences, scalars) equal field by field; floats to 1e-9."""
    if hasattr(a, "get_fields_and_field_types"):
        assert type(a) is type(b), where
        for name in a.get_fields_and_field_types():
            _assert_same(getattr(a, name), getattr(b, name), f"{where}.{name}")
    elif isinstance(a, np.ndarray):
        assert a.shape == b.shape and a.dtype == b.dtype, where
        if a.dtype.kind == "f":
            np.testing.assert_allclose(a, b, atol=1e-9, err_msg=where)
        else:
            np.testing.assert_array_equal(a, b, err_msg=where)
    elif isinstance(a, (list, tuple)) or type(a).__name__ == "array":
        a, b = list(a), list(b)
        assert len(a) == len(b), where
        for k, (x, y) in enumerate(zip(a, b, strict=True)):
            _assert_same(x, y, f"{where}[{k}]")
    elif isinstance(a, float):
        assert a == pytest.approx(b, abs=1e-9), where
    elif isinstance(a, str) and where == "/session/info.data":
        assert _same_json(json.loads(a), json.loads(b)), where
    else:
        assert a == b, where


def _same_json(a, b):
    """JSON values equal; floats to 1e-9."""
    if isinstance(a, dict):
        return a.keys() == b.keys() and all(_same_json(a[k], b[k]) for k in a)
    if isinstance(a, list):
        return len(a) == len(b) and all(_same_json(x, y) for x, y in zip(a, b, strict=True))
    if isinstance(a, float):
        return abs(a - b) <= 1e-9
    return a == b


def test_readme_and_makefile_regenerate_the_shipped_bags():
    """bags/README.md lists one command per shipped bag, and `make bags` runs the same commands."""
    commands = _readme_commands()
    assert sorted(commands) == sorted(p.name for p in BAGS.iterdir() if p.is_dir())
    makefile = re.sub(r"\\\n\s*", "", (REPO / "Makefile").read_text())
    for argv in commands.values():
        assert "python -m body_scheme_apps.record " + " ".join(argv) in makefile


@pytest.mark.parametrize("name", sorted(_readme_commands()))
def test_regenerated_bag_equals_shipped_bag(name, tmp_path):
    """Running a bag's documented command again gives the same decoded messages as the shipped bag."""
    argv = list(_readme_commands()[name])
    argv[argv.index("--out") + 1] = str(tmp_path / name)
    assert record.main(argv) == 0
    shipped, fresh = list(read_messages(BAGS / name)), list(read_messages(tmp_path / name))
    assert len(shipped) == len(fresh) and {m.topic for m in shipped} <= set(SESSION_TOPICS)
    for k, (a, b) in enumerate(zip(shipped, fresh, strict=True)):
        assert (a.topic, a.log_time) == (b.topic, b.log_time), k
        _assert_same(a.msg, b.msg, a.topic if a.topic == "/session/info" else f"{a.topic}[{k}]")
