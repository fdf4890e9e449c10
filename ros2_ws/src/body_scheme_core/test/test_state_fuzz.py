"""Checkpoint fuzz: a real state file mutated 1,000 ways is refused with ModelFileError or loads, and a loaded learner
then runs 50 steps and what a node calls first without an exception (issue 20).

``python ros2_ws/src/body_scheme_core/test/test_state_fuzz.py 5000`` runs more mutations and prints the failures.
"""

from __future__ import annotations

import json
import sys

import numpy as np

from body_scheme_core.config import BodySchemeConfig
from body_scheme_core.errors import InvalidInputError, ModelFileError
from body_scheme_core.learned_body import learned_tree, learned_urdf
from body_scheme_core.learner import BodySchemeLearner
from body_scheme_core.persistence import encode_state, load_state
from body_scheme_core.world import Fault, make_session, planar_2dof

N_MUTATIONS = 1000
HUGE = "9" * 5000
DEEP = "[" * 100_000 + "]" * 100_000
REPLACEMENTS = [0, -1, 1, 10**30, 1e308, -1e308, 0.5, 2.5, "x", "inf", None, True, False, [], {}, [1, 2], {"a": 1}]


def _state_and_session():
    """A small learner after bootstrapping and a blocked joint (tree, memory, mismatch and calibration filled)."""
    robot = planar_2dof()
    session = make_session(robot, 160, seed=3, sigma_trans=0.01, sigma_rot=np.radians(3.0), visibility=0.9,
                           faults=[(100, Fault("block_joint", action_index=1, angle=0.4))])
    learner = BodySchemeLearner(robot.marker_ids, robot.n_actions,
                                BodySchemeConfig(train_window=20, test_window=10, history_length=40),
                                action_lower=robot.action_lower, action_upper=robot.action_upper)
    for k in range(140):
        learner.update(session.actions[k], session.observations[k])
    return encode_state(learner), robot, session


def _paths(value, prefix=()):
    yield prefix
    if isinstance(value, dict):
        for key, item in value.items():
            yield from _paths(item, (*prefix, key))
    elif isinstance(value, list):
        for index, item in enumerate(value):
            yield from _paths(item, (*prefix, index))


def _get(document, path):
    for key in path:
        document = document[key]
    return document


def mutations(text, n, seed=0):
    """``n`` mutated state texts with a description each (deterministic)."""
    rng = np.random.default_rng(seed)
    document = json.loads(text)
    paths = [p for p in _paths(document) if len(p) >= 2]  # inside "state" or the header
    for _ in range(n):
        path = paths[int(rng.integers(len(paths)))]
        operator = str(rng.choice(["replace", "replace", "delete", "add_key", "duplicate", "drop", "reverse", "swap",
                                   "huge", "deep", "text"]))
        doc = json.loads(text)
        parent, key = _get(doc, path[:-1]), path[-1]
        marker = None
        if operator == "replace":
            parent[key] = REPLACEMENTS[int(rng.integers(len(REPLACEMENTS)))]
        elif operator == "delete":
            del parent[key]
        elif operator == "add_key" and isinstance(parent[key], dict):
            parent[key]["unknown_key"] = 1
        elif operator in ("duplicate", "drop", "reverse") and isinstance(parent[key], list) and parent[key]:
            items = parent[key]
            parent[key] = (items + items[-1:] if operator == "duplicate" else items[:-1] if operator == "drop"
                           else items[::-1])
        elif operator == "swap":
            other = paths[int(rng.integers(len(paths)))]
            parent[key] = json.loads(json.dumps(_get(json.loads(text), other)))
        elif operator in ("huge", "deep"):
            parent[key] = marker = "@@MARK@@"
        mutated = json.dumps(doc, separators=(",", ":"))
        if marker is not None:
            mutated = mutated.replace('"@@MARK@@"', HUGE if operator == "huge" else DEEP, 1)
        if operator == "text":
            cut = int(rng.integers(len(text)))
            mutated = text[:cut] + (chr(int(rng.integers(32, 127))) if rng.random() < 0.5 else "") + text[cut + 1:]
        yield f"{operator} at {'/'.join(map(str, path))}", mutated


def first_uses(learner, robot, session):
    """What scheme_node does with a freshly loaded learner, then 50 learning steps."""
    learner.edge_status()
    learner.noise.axis_sigmas()
    lower, upper = learner.trained_range()
    scheme = learner.body_scheme
    if scheme is not None:
        learner.predict(session.actions[0], return_std=True)
        learned_urdf(learned_tree(scheme, robot.action_joint_names, lower, upper))
    encode_state(learner)
    for k in range(50):
        try:
            learner.update(session.actions[100 + k], session.observations[100 + k])
        except InvalidInputError:  # a refusal the mutated limits or step order call for, not a crash
            pass
    learner.edge_status()


def run(n, tmp_path):
    """Failures ``(description, exception)`` of ``n`` mutations, and how many loaded."""
    text, robot, session = _state_and_session()
    failures, loaded = [], 0
    path = tmp_path / "state.json"
    for description, mutated in mutations(text, n):
        path.write_text(mutated)
        try:
            learner = load_state(path)
        except ModelFileError:
            continue
        except Exception as error:
            failures.append((f"load: {description}", repr(error)[:300]))
            continue
        loaded += 1
        try:
            first_uses(learner, robot, session)
        except Exception as error:
            failures.append((f"use: {description}", repr(error)[:300]))
    return failures, loaded


def test_every_mutation_of_a_state_file_is_refused_or_loads_into_a_learner_that_works(tmp_path):
    failures, loaded = run(N_MUTATIONS, tmp_path)
    assert loaded > 50  # the mutations reach the learner, not only the parser
    assert not failures, "\n".join(f"{d}: {e}" for d, e in failures[:30]) + f"\n({len(failures)} failures)"


if __name__ == "__main__":
    import pathlib
    import tempfile

    with tempfile.TemporaryDirectory() as tmp:
        found, n_loaded = run(int(sys.argv[1]) if len(sys.argv) > 1 else N_MUTATIONS, pathlib.Path(tmp))
    print(f"{n_loaded} loaded, {len(found)} failures")
    for d, e in found:
        print(d, e)
