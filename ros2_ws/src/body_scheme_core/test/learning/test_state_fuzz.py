"""Checkpoint fuzz: real learner state files mutated 1,000 ways are each refused with ``ModelFileError`` by
``load_state`` or load into a learner that then works: what scheme_node calls on a freshly loaded learner
(``edge_status``, ``body_scheme``, ``predict``, ``noise.axis_sigmas``, ``trained_range``, ``learned_tree`` and
``learned_urdf``, ``encode_state``), 50 ``update`` steps of the same robot's session (refusals of inputs,
``InvalidInputError``, are fine; ``LearnerStepError`` or anything else is not), and the state it then saves loads
again.

The states come from a real run: the 2-DOF planar robot bootstraps, then both joints block one after the other and are
repaired; the states are taken while the tree is of candidates, while an edge is in mismatch and its replacement is
refined (memory, replacement candidates in both batches, the joint fit, the learned noise, a rejected observation),
while parts are not explained by the joint fit, and after a remembered model was reinstated (its prior). Every
mutation is one document: a random field (fields are drawn uniformly by their place in the layout, list indices
ignored, so a rare field is hit as often as a pose entry) and an operator on numbers (0, -1, 1, sign, 0.5 for an int,
an int for a float, int64-sized and 5000-digit integers, 1e308), types (string, "inf", null, true, lists, dicts),
structure (delete or add a key, duplicate, drop, truncate, reverse or empty a list, swap two values of the same type
or of the same field from different places), deep nesting, or the text (truncate, flip a bit, change a digit, delete
or insert a character).

The mutations are shared among two processes (``BODY_SCHEME_FUZZ_WORKERS``); each may take :data:`CPU_BUDGET` CPU
seconds and the loop at most :data:`MEMORY_BUDGET` more memory. More mutations: ``python
ros2_ws/src/body_scheme_core/test/learning/test_state_fuzz.py 5000 [seed]`` prints every failure, or the environment
variables ``BODY_SCHEME_FUZZ_MUTATIONS`` and ``BODY_SCHEME_FUZZ_SEED`` for the pytest run. Mutation ``i`` of a seed is
always the same document (:func:`mutation`), so a failure's ``#i`` reproduces it.
"""

from __future__ import annotations

import contextlib
import json
import math
import multiprocessing
import os
import resource
import signal
import sys
import threading
import time
import traceback
import warnings
from collections import Counter, defaultdict
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pytest

from body_scheme_core.errors import InvalidInputError, ModelFileError
from body_scheme_core.learning.config import BodySchemeConfig
from body_scheme_core.learning.learner import BodySchemeLearner
from body_scheme_core.learning.persistence import encode_state, load_state, save_state
from body_scheme_core.prediction.learned_body import learned_tree, learned_urdf
from body_scheme_core.world import REPAIR, Fault, make_session, planar_2dof

N_MUTATIONS = int(os.environ.get("BODY_SCHEME_FUZZ_MUTATIONS", "120"))  # make fuzz: 3,000
SEED = int(os.environ.get("BODY_SCHEME_FUZZ_SEED", "0"))
#: Processes the mutations are shared among.
WORKERS = int(os.environ.get("BODY_SCHEME_FUZZ_WORKERS", str(min(2, os.cpu_count() or 1))))
#: Learning steps run on every learner that loads.
N_STEPS = 50
#: CPU seconds one mutation may take (load, queries and steps; about 0.3 s normally) before it counts as a failure.
CPU_BUDGET = 10.0
#: Address space the fuzz loop may add to the process (a mutated capacity must not allocate the machine's memory).
MEMORY_BUDGET = 4 << 30
#: Failures printed by the assertion.
N_PRINTED = 30

# The session and the learner the states come from (small: every loaded learner runs 50 steps).
N_SESSION = 200
CONFIG = {"train_window": 15, "test_window": 8, "history_length": 30, "root_window": 8, "memory_size": 2}
FAULTS = ((60, Fault("block_joint", action_index=1, angle=0.4)), (64, Fault("block_joint", action_index=0, angle=-0.3)),
          (110, REPAIR))
OUTLIER_STEP = 50  # marker 3 seen 40 m away: a rejected observation (``rejected``)

HUGE_INTEGER = "7" * 5000  # Python refuses to convert it; JSON has no limit
DEEP_NESTING = "[" * 100_000 + "]" * 100_000  # as text: json.dumps would recurse
MARK = "\x00fuzz-mark\x00"  # stands for raw text spliced into the dumped document

#: Replacements of any value (the types), and of numbers.
TYPE_VALUES = ("x", "", "inf", "-inf", "nan", None, True, False, [], {}, [1, 2], [[0.0]], {"a": 1}, "revolute", 0, 1.5)
NUMBER_VALUES = (0, -1, 1, 2, 0.0, -0.0, 1e-300, 1e308, -1e308, 2**31, 2**53 + 1, 2**63 - 1, 2**63, 10**19, -10**19,
                 -(2**63))


# ---------------------------------------------------------------------------------------------- the real states
@dataclass
class Base:
    """A real state file and what continues it.

    Attributes
    ----------
    name : str
        What the state holds (``bootstrapping``, ``refining``, ``unexplained``).
    text : str
        The state file's text, as ``save_state`` wrote it.
    start : int
        Session step the learner takes next (the 50 steps are ``start .. start + 49``).
    document : dict
        ``text`` parsed.
    paths : dict of tuple to list of tuple
        Concrete JSON paths of every value by their schema (the path with list indices as ``"*"``).
    by_type : dict of str to list of tuple
        Concrete JSON paths by the type of their value.
    schemas : list of tuple
        The keys of ``paths``, sorted.
    """

    name: str
    text: str
    start: int
    document: dict = field(init=False)
    paths: dict = field(init=False)
    by_type: dict = field(init=False)
    schemas: list = field(init=False)

    def __post_init__(self):
        self.document = json.loads(self.text)
        self.paths, self.by_type = defaultdict(list), defaultdict(list)
        for path, value in _walk(self.document):
            if path:
                self.paths[tuple("*" if isinstance(k, int) else k for k in path)].append(path)
                self.by_type[_type_name(value)].append(path)
        self.schemas = sorted(self.paths, key=str)


@dataclass
class Robot:
    """The robot of the states and its session."""

    part_ids: tuple
    joint_names: tuple
    actions: np.ndarray
    observations: list


def _walk(value, path=()):
    """``(path, value)`` of ``value`` and everything inside it, depth first."""
    yield path, value
    if isinstance(value, dict):
        for key, item in value.items():
            yield from _walk(item, (*path, key))
    elif isinstance(value, list):
        for index, item in enumerate(value):
            yield from _walk(item, (*path, index))


def _type_name(value):
    return "null" if value is None else type(value).__name__


def _non_trivial(state):
    """Fields of a learner state that are not empty."""
    roles = Counter(e["role"] for e in state["entries"])
    names = [k for k in ("mismatch", "refining", "failed", "vetoed", "unexplained", "lack_of_fit", "rejected",
                         "calibration", "last_stamp", "history", "root_samples") if state[k]]
    names += [f"{role} models" for role in roles]
    if any(slot is not None for slot in state["gp_batch"].get("slots", [])):
        names.append("gp_batch slots")
    if any(slot is not None for slot in state["rigid_batch"].get("slots", [])):
        names.append("rigid_batch slots")
    if any(e["prior"] is not None for e in state["entries"]):
        names.append("priors")
    return set(names)


def build_states(tmp_path):
    """The real states (:class:`Base`) and the robot's session, from one run of the learner.

    The learner bootstraps on the planar 2-DOF robot, sees one observation 40 m away, then joint 2 and joint 1 block
    at steps 60 and 64 and are repaired at 110. A state is saved (``save_state``) the first time the learner is
    bootstrapping with a tree of candidates, has an edge in mismatch while another's replacement is refined, has
    parts the joint fit does not explain, and has reinstated a remembered model (which carries a prior).
    """
    robot = planar_2dof()
    session = make_session(robot, N_SESSION, seed=3, sigma_trans=0.01, sigma_rot=math.radians(3.0), visibility=0.9,
                           faults=FAULTS)
    learner = BodySchemeLearner(robot.marker_ids, robot.n_actions, BodySchemeConfig(**CONFIG),
                                action_lower=robot.action_lower, action_upper=robot.action_upper)
    wanted = {
        "bootstrapping": lambda s: s["bootstrapping"] and s["tree"] is not None and s["calibration"] is not None,
        "refining": lambda s: s["mismatch"] and s["refining"] and s["rejected"],
        "unexplained": lambda s: (s["unexplained"] or s["lack_of_fit"]) and s["mismatch"],
        "reinstated": lambda s: any(e["prior"] is not None for e in s["entries"]),
    }
    bases = {}
    for k in range(N_SESSION - N_STEPS):
        observations = session.observations[k]
        if k == OUTLIER_STEP and 3 in observations:
            observations = dict(observations)
            observations[3] = observations[3].copy()
            observations[3][:3, 3] += 40.0
        learner.update(session.actions[k], observations, stamp=0.1 * k)
        state = learner.to_state()
        for name, test in wanted.items():
            if name not in bases and test(state):
                path = tmp_path / f"{name}.json"
                save_state(learner, path)
                bases[name] = Base(name, path.read_text(), k + 1)
        if len(bases) == len(wanted):
            break
    covered = set().union(*(_non_trivial(b.document["state"]) for b in bases.values()))
    needed = {"mismatch", "refining", "failed", "calibration", "rejected", "memory models", "candidate models",
              "tree models", "gp_batch slots", "rigid_batch slots", "priors"}
    assert needed <= covered, f"the run no longer makes states with {sorted(needed - covered)}; adjust it"
    return list(bases.values()), Robot(tuple(robot.marker_ids), tuple(robot.action_joint_names),
                                       np.asarray(session.actions), session.observations)


# ---------------------------------------------------------------------------------------------- mutations
@dataclass
class Mutation:
    """One mutated state file: what was done to which state, and the file's bytes."""

    base: Base
    description: str
    data: bytes


def _get(document, path):
    for key in path:
        document = document[key]
    return document


def _copy(value):
    return json.loads(json.dumps(value))


def _short(value):
    text = json.dumps(value) if not isinstance(value, str) or MARK not in value else value
    return text if len(text) <= 60 else f"{text[:57]}..."


def _pick(rng, items):
    return items[int(rng.integers(len(items)))]


def _number_ops(value):
    ops = ["number", "number", "negate", "plus_one", "minus_one", "scale"]
    ops.append("int_to_float" if isinstance(value, int) else "float_to_int")
    return ops


def _apply(rng, base, document, path):
    """Mutate the value at ``path`` of ``document`` in place; returns ``(operator, new value description, raw)``
    where ``raw`` is text to splice in for :data:`MARK` (or None)."""
    parent, key = _get(document, path[:-1]), path[-1]
    value = parent[key]
    ops = ["type", "delete", "swap_type", "swap_field", "swap_field", "huge_integer", "deep_nesting", "big_integer"]
    if isinstance(value, bool):
        ops += ["flip", "flip", "bool_to_int"]
    elif isinstance(value, (int, float)):
        ops += _number_ops(value) * 2
    elif isinstance(value, list):
        ops += ["duplicate", "drop", "truncate", "reverse", "empty", "append", "shuffle"] * 2
    elif isinstance(value, dict):
        ops += ["add_key", "drop_key", "empty"] * 2
    elif isinstance(value, str):
        ops += ["string", "long_string"]
    elif value is None:
        ops += ["null_number", "swap_field", "swap_field"]
    op = _pick(rng, ops)
    raw = None
    if op == "type":
        new = _copy(_pick(rng, TYPE_VALUES))
    elif op in ("number", "null_number"):
        new = _pick(rng, NUMBER_VALUES)
    elif op == "big_integer":
        new = _pick(rng, (2**63, 10**19, -10**19, 2**64 - 1))
    elif op == "huge_integer":
        new, raw = MARK, HUGE_INTEGER
    elif op == "deep_nesting":
        new, raw = MARK, DEEP_NESTING
    elif op == "delete":
        if isinstance(parent, dict):
            del parent[key]
        else:
            parent.pop(key)
        return op, "", None
    elif op == "swap_type" or op == "swap_field":
        pool = base.by_type[_type_name(value)] if op == "swap_type" else base.paths[
            tuple("*" if isinstance(k, int) else k for k in path)]
        others = [p for p in (_pick(rng, pool) for _ in range(8)) if p != path and _get(base.document, p) != value]
        if not others:
            new = _copy(_pick(rng, TYPE_VALUES))
            op = "type"
        else:
            other = others[0]
            new = _copy(_get(base.document, other))
            independent = other[:len(path)] != path and path[:len(other)] != other
            if independent:  # the other place gets this value: a swap; else only a copy
                _get(document, other[:-1])[other[-1]] = _copy(value)
            op = f"{'swap' if independent else 'copy'} with {'/'.join(map(str, other))}"
    elif op == "flip":
        new = not value
    elif op == "bool_to_int":
        new = int(value)
    elif op == "negate":
        new = -value
    elif op == "plus_one":
        new = value + 1
    elif op == "minus_one":
        new = value - 1
    elif op == "scale":
        new = value * _pick(rng, (1e6, 1e-6, 1e12, 3))
    elif op == "int_to_float":
        new = value + 0.5
    elif op == "float_to_int":
        new = int(round(value)) if math.isfinite(value) and abs(value) < 1e18 else 0
    elif op == "duplicate":
        new = list(value)
        if new:
            i = int(rng.integers(len(new)))
            new.insert(i, _copy(new[i]))
        op = f"duplicate an element of {len(value)}"
    elif op == "drop":
        new = list(value)
        if new:
            i = int(rng.integers(len(new)))
            del new[i]
            op = f"drop element {i} of {len(value)}"
    elif op == "truncate":
        n = int(rng.integers(len(value))) if value else 0
        new = value[:n]
        op = f"truncate {len(value)} to {n}"
    elif op == "reverse":
        new = value[::-1]
    elif op == "shuffle":
        new = [value[i] for i in rng.permutation(len(value))]
    elif op == "empty":
        new = type(value)()
    elif op == "append":
        new = [*value, _copy(value[-1] if value and rng.random() < 0.5 else _pick(rng, TYPE_VALUES))]
    elif op == "add_key":
        new = dict(value, unknown_key=_copy(_pick(rng, TYPE_VALUES)))
    elif op == "drop_key":
        new = dict(value)
        if new:
            dropped = _pick(rng, sorted(new))
            del new[dropped]
            op = f"drop key {dropped!r}"
    elif op == "string":
        new = _pick(rng, ("", "x", "tree", "memory", "candidate", "gp", "static", "prismatic", "revolute", "GPBatch",
                          "RigidBatch", "body_scheme", "auto", "1", "\u00e9\u6f22", "\ud800"))
    elif op == "long_string":
        new = "x" * 1_000_000
    else:  # pragma: no cover - every operator is handled above
        raise AssertionError(op)
    parent[key] = new
    return op, _short(new) if raw is None else f"<{len(raw)} characters>", raw


def _text_mutation(rng, data):
    """A mutation of the file's bytes."""
    op = _pick(rng, ("truncate", "flip_bit", "digit", "digit", "delete", "insert", "overflow"))
    i = int(rng.integers(len(data)))
    if op == "truncate":
        return f"text: truncated to {i} of {len(data)} bytes", data[:i]
    if op == "flip_bit":
        bit = int(rng.integers(8))
        return f"text: bit {bit} of byte {i} flipped", data[:i] + bytes([data[i] ^ (1 << bit)]) + data[i + 1:]
    if op == "digit":  # bit rot that keeps the JSON valid: another number
        digits = [j for j in rng.integers(len(data), size=64) if chr(data[j]).isdigit()]
        if digits:
            j = int(digits[0])
            new = str(int(rng.integers(10))).encode()
            context = data[max(0, j - 25):j + 5].decode("utf-8", "replace")
            return f"text: digit at {j} ({context!r}) -> {new.decode()}", data[:j] + new + data[j + 1:]
    if op == "delete":
        return f"text: byte {i} ({chr(data[i])!r}) deleted", data[:i] + data[i + 1:]
    if op == "insert":
        c = _pick(rng, (b",", b"]", b"}", b"[", b"{", b'"', b"-", b"0", b"9", b" ", b"e", b"\x00", b"\xff"))
        return f"text: {c!r} inserted at {i}", data[:i] + c + data[i:]
    j = data.find(b"e-", i)
    if j < 0:
        j = data.find(b".", i)
    return f"text: 1e999 inserted at {j}", data[:j] + b"1e999" + data[j:]


def mutation(bases, index, seed=SEED):
    """Mutation number ``index`` (:class:`Mutation`): the same for the same ``bases``, ``index`` and ``seed``."""
    rng = np.random.default_rng([seed, index])
    base = _pick(rng, bases)
    if rng.random() < 0.1:
        description, data = _text_mutation(rng, base.text.encode())
        return Mutation(base, f"#{index} [{base.name}] {description}", data)
    document = json.loads(base.text)
    path = _pick(rng, base.paths[_pick(rng, base.schemas)])
    op, new, raw = _apply(rng, base, document, path)
    text = json.dumps(document, separators=(",", ":"), ensure_ascii=False)
    if raw is not None:
        text = text.replace(json.dumps(MARK), raw, 1)
    where = "/".join(map(str, path))
    return Mutation(base, f"#{index} [{base.name}] {where}: {op}{' -> ' + new if new else ''}",
                    text.encode("utf-8", "surrogatepass"))


# ---------------------------------------------------------------------------------------------- using a learner
class TooSlow(BaseException):
    """A mutation took more than :data:`CPU_BUDGET` CPU seconds (a BaseException: the library must not catch it)."""


@dataclass
class Failure:
    """A mutation that neither was refused with ModelFileError nor loaded into a learner that works."""

    index: int
    description: str
    stage: str
    error: str
    where: str

    @property
    def kind(self):
        """What tells failures apart: stage, exception and where it was raised."""
        return f"{self.stage.split('[')[0]}: {self.error.split(':')[0]} at {self.where}"

    def __str__(self):
        return f"{self.description}\n    {self.stage}: {self.error}\n    at {self.where}"


def _innermost(error):
    """The exception that started it (following ``__cause__``, e.g. of a LearnerStepError)."""
    seen = set()
    while error.__cause__ is not None and id(error) not in seen:
        seen.add(id(error))
        error = error.__cause__
    return error


def _describe(error):
    """``(exception text, where)``: the error (and its cause) and the last frames in body_scheme_core and beyond."""
    inner = _innermost(error)
    text = f"{type(inner).__name__}: {' '.join(str(inner).split())[:300]}"
    if inner is not error:
        text = f"{type(error).__name__} <- {text}"
    frames = traceback.extract_tb(inner.__traceback__)
    ours = [f for f in frames if "body_scheme_core" in os.path.realpath(f.filename) and "/test/" not in f.filename]
    where = "?"
    if ours:
        f = ours[-1]
        where = f"{os.path.relpath(os.path.realpath(f.filename), _SOURCE_ROOT)}:{f.lineno} in {f.name}"
    if frames and (not ours or frames[-1] is not ours[-1]):
        f = frames[-1]
        where += f" -> {Path(f.filename).name}:{f.lineno} in {f.name}"
    return text, where


_SOURCE_ROOT = str(Path(__file__).resolve().parents[2])


def _actions_for(robot, k, n_actions):
    """The session's action ``k``, cut or padded with zeros to ``n_actions`` (a learner of another size)."""
    a = np.zeros(n_actions)
    m = min(n_actions, robot.actions.shape[1])
    a[:m] = robot.actions[k][:m]
    return a


def use(learner, robot, start, path, stage):
    """What scheme_node does with a freshly loaded learner, 50 learning steps, the same again and a reload of its
    saved state. ``stage`` (a one-element list) names the call under way."""
    n = learner.n_actions
    names = tuple(robot.joint_names[:n]) + tuple(f"extra_joint{k}" for k in range(len(robot.joint_names), n))

    def queries():
        stage[0] = "edge_status"
        learner.edge_status()
        stage[0] = "body_scheme"
        scheme = learner.body_scheme
        stage[0] = "noise.axis_sigmas"
        learner.noise.axis_sigmas()
        stage[0] = "trained_range"
        lower, upper = learner.trained_range()
        if scheme is not None:
            stage[0] = "predict"
            learner.predict(_actions_for(robot, start, n), return_std=True)
            stage[0] = "learned_tree"
            body = learned_tree(scheme, names, lower, upper)
            stage[0] = "learned_urdf"
            learned_urdf(body)
        stage[0] = "encode_state"
        return encode_state(learner)

    queries()
    for k in range(N_STEPS):
        stage[0] = f"update[{k}]"
        try:
            learner.update(_actions_for(robot, start + k, n), robot.observations[start + k])
        except InvalidInputError:  # a refusal the mutated limits or sizes call for, not a crash
            pass
    text = queries()
    stage[0] = "reload of the state it saved"
    path.write_text(text)
    load_state(path)


@contextlib.contextmanager
def _guards():
    """Per mutation: raise :class:`TooSlow` after :data:`CPU_BUDGET` CPU seconds; for the whole loop: at most
    :data:`MEMORY_BUDGET` more address space (a MemoryError instead of the machine's memory). Main thread, Linux."""
    if threading.current_thread() is not threading.main_thread() or not hasattr(signal, "SIGVTALRM"):
        yield lambda: contextlib.nullcontext()
        return

    def too_slow(signum, frame):
        raise TooSlow(f"more than {CPU_BUDGET} CPU seconds")

    @contextlib.contextmanager
    def budget():
        signal.setitimer(signal.ITIMER_VIRTUAL, CPU_BUDGET)
        try:
            yield
        finally:
            signal.setitimer(signal.ITIMER_VIRTUAL, 0)

    previous = signal.signal(signal.SIGVTALRM, too_slow)
    limits = resource.getrlimit(resource.RLIMIT_AS)
    try:
        with open("/proc/self/status") as f:
            size = next(int(line.split()[1]) * 1024 for line in f if line.startswith("VmSize:"))
        soft = size + MEMORY_BUDGET
        if limits[1] != resource.RLIM_INFINITY:
            soft = min(soft, limits[1])
        resource.setrlimit(resource.RLIMIT_AS, (soft, limits[1]))
    except (OSError, ValueError, StopIteration):
        limits = None
    try:
        yield budget
    finally:
        signal.setitimer(signal.ITIMER_VIRTUAL, 0)
        signal.signal(signal.SIGVTALRM, previous)
        if limits is not None:
            resource.setrlimit(resource.RLIMIT_AS, limits)


@dataclass
class Report:
    """What a fuzz run found."""

    n: int = 0
    refused: int = 0
    loaded: int = 0
    failures: list = field(default_factory=list)
    slowest: list = field(default_factory=list)

    def add(self, other):
        """Count ``other`` (another worker's report) in."""
        self.n, self.refused, self.loaded = self.n + other.n, self.refused + other.refused, self.loaded + other.loaded
        self.failures = sorted(self.failures + other.failures, key=lambda f: f.index)
        self.slowest = sorted(self.slowest + other.slowest)[-5:]

    def summary(self, n_printed=N_PRINTED):
        """The failures: counts per kind, then the first ``n_printed``."""
        kinds = Counter(f.kind for f in self.failures)
        lines = [f"{self.n} mutations: {self.refused} refused (ModelFileError), {self.loaded} loaded, "
                 f"{len(self.failures)} failures of {len(kinds)} kinds"]
        lines += [f"  {count:4d} x {kind}" for kind, count in kinds.most_common()]
        lines += [str(f) for f in self.failures[:n_printed]]
        return "\n".join(lines)


def _run_share(bases, robot, indices, seed, tmp_path):
    """Mutations ``indices``, one after the other: a :class:`Report`."""
    report = Report()
    path, resaved = Path(tmp_path) / "mutated.json", Path(tmp_path) / "resaved.json"
    with _guards() as budget, _one_thread(), warnings.catch_warnings():
        warnings.simplefilter("ignore")  # overflow in a mutated state's arithmetic: what matters is what it raises
        for index in indices:
            m = mutation(bases, index, seed)
            report.n += 1
            path.write_bytes(m.data)
            stage = ["load_state"]
            t0 = time.process_time()
            try:
                with budget():
                    try:
                        learner = load_state(path)
                    except ModelFileError:
                        report.refused += 1
                        continue
                    report.loaded += 1
                    use(learner, robot, m.base.start, resaved, stage)
            except (Exception, TooSlow) as error:
                report.failures.append(Failure(index, m.description, stage[0], *_describe(error)))
            finally:
                report.slowest = sorted([*report.slowest, (time.process_time() - t0, m.description)])[-5:]
    return report


@contextlib.contextmanager
def _one_thread():
    """BLAS on one thread (its matrices are small; the workers use the cores)."""
    try:
        from threadpoolctl import threadpool_limits
    except ImportError:
        yield
        return
    with threadpool_limits(1):
        yield


def run(bases, robot, n, tmp_path, seed=SEED, workers=WORKERS):
    """Load mutations ``0 .. n-1`` of ``bases`` and use every learner that loads (:func:`use`), in ``workers``
    processes; returns a :class:`Report`."""
    shares = [range(w, n, workers) for w in range(workers)]
    dirs = [Path(tmp_path) / f"worker{w}" for w in range(workers)]
    for d in dirs:
        d.mkdir(exist_ok=True)
    if workers == 1 or "fork" not in multiprocessing.get_all_start_methods():
        reports = [_run_share(bases, robot, share, seed, d) for share, d in zip(shares, dirs, strict=True)]
    else:
        with multiprocessing.get_context("fork").Pool(workers) as pool:
            reports = pool.starmap(_run_share, [(bases, robot, share, seed, d) for share, d in zip(shares, dirs,
                                                                                                    strict=True)])
    report = Report()
    for r in reports:
        report.add(r)
    return report


# ---------------------------------------------------------------------------------------------- tests
@pytest.fixture(scope="module")
def states(tmp_path_factory):
    """The real states and the robot's session (:func:`build_states`)."""
    return build_states(tmp_path_factory.mktemp("states"))


def test_the_real_states_load_and_work(states, tmp_path):
    """Unmutated, every state loads, works and saves a state that loads again."""
    bases, robot = states
    for base in bases:
        path = tmp_path / "state.json"
        path.write_text(base.text)
        use(load_state(path), robot, base.start, tmp_path / "resaved.json", [""])


@pytest.mark.timeout(1200)  # CPU-bound and always advancing: on a busy machine several times 300 s
@pytest.mark.slow
def test_every_mutation_of_a_state_file_is_refused_or_loads_into_a_learner_that_works(states, tmp_path):
    """``N_MUTATIONS`` mutations (:func:`mutations`; 120 here, 3,000 in ``make fuzz``): each is refused with
    ModelFileError, or the learner it loads into answers scheme_node's queries, learns 50 steps and saves a state that
    loads again, without an exception."""
    bases, robot = states
    report = run(bases, robot, N_MUTATIONS, tmp_path)
    assert report.loaded > N_MUTATIONS // 10, report.summary()  # the mutations reach the learner, not only the parser
    assert not report.failures, report.summary()


if __name__ == "__main__":
    import tempfile

    count = int(sys.argv[1]) if len(sys.argv) > 1 else N_MUTATIONS
    seed = int(sys.argv[2]) if len(sys.argv) > 2 else SEED
    with tempfile.TemporaryDirectory() as tmp:
        t_start = time.perf_counter()
        built_bases, built_robot = build_states(Path(tmp))
        result = run(built_bases, built_robot, count, tmp, seed=seed)
    print(result.summary(n_printed=len(result.failures)))
    print(f"{time.perf_counter() - t_start:.1f} s; slowest mutations (CPU s):")
    for seconds, description in reversed(result.slowest):
        print(f"  {seconds:.2f} {description}")
    sys.exit(1 if result.failures else 0)
