"""``replay_offline``: run scheme_node's learning straight over a recorded session, without a ROS graph.

Examples::

    replay_offline bags/joint_blocked_seed0 --out out/replay/joint_blocked_seed0
    python -m body_scheme_apps.replay_offline BAG --params my_scheme_node.yaml --part 7

The learning loop is :func:`body_scheme_nodes.offline_replay.replay_bag`: the bag's ``/joint_commands`` and
``/observations`` are decoded into rclpy messages (:mod:`~body_scheme_nodes.bag_io`) and go through exactly
scheme_node's code: settings from its parameter file
(:meth:`~body_scheme_nodes.settings.SchemeSettings.from_yaml`, default: the shipped ``config/scheme_node.yaml``),
:func:`~body_scheme_nodes.message_feed.feed_message` into the pairer, ``learner.update`` per sample, and a final
``flush(inf)``. So replaying the bag through the graph (``bag_replay`` -> ``scheme_node``) ends with the same body
scheme and the same events.

Writes to ``--out``:

``report.json``
    settings, one record per learning step (stamp, phase, each tree edge's test-window errors, the end effector's
    prediction error against ``/ground_truth/marker_poses`` if recorded), the events, the final structure, the mean
    end-effector error per fault block.
``events.txt``
    the timeline of the learner's decisions, with the session's faults.
``errors.png``
    error over time per edge and of the end effector, fault blocks shaded and events marked (the paper's Fig. 5, 6).

The end effector's prediction for a step is made *before* the learner sees that step's observation, from the
command alone; it is compared with the ground-truth message stamped at or right after the command.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import pathlib
import sys
import textwrap
from collections import Counter

import numpy as np
from tqdm import tqdm

from body_scheme_core.errors import BodySchemeError
from body_scheme_nodes.bag_io import bag_topics
from body_scheme_nodes.offline_replay import COMMANDS, default_params_file, replay_bag
from body_scheme_nodes.settings import SchemeSettings
from body_scheme_nodes.sources import SourceMap

from .entry import command

__all__ = ["build_report", "default_part", "fault_blocks", "format_timeline", "format_summary", "plot_errors",
           "main"]

#: Events marked in the plot, with their line style.
_MARKED_EVENTS = {"mismatch_detected": ("tab:red", "--"), "model_replaced": ("tab:blue", "-"),
                  "model_reinstated": ("tab:green", "-"), "structure_found": ("black", ":"),
                  "bootstrap_finished": ("black", "-.")}


def default_part(edges, root):
    """The part farthest from the root in a tree given as ``[(parent, child), ...]`` (highest id on ties)."""
    depth = {root: 0}
    children = {}
    for parent, child in edges:
        children.setdefault(parent, []).append(child)
    frontier = [root]
    while frontier:
        part = frontier.pop()
        for child in children.get(part, []):
            depth[child] = depth[part] + 1
            frontier.append(child)
    return max(depth, key=lambda part: (depth[part], part))


def fault_blocks(info, n_commands):
    """The session's fault timeline as blocks ``[{start, stop, label, fault}]`` of command indices.

    ``label`` is ``normal`` before the first entry, else the entry without its step (e.g. ``block_joint:5:0.8``);
    ``fault`` tells whether the robot is faulty in the block (any entry but ``repair``).
    """
    entries = sorted((int(step), str(text)) for step, text in (info or {}).get("faults", []))
    starts = [0] + [step for step, _ in entries]
    labels = ["normal"] + [_short_label(text) for _, text in entries]
    blocks = []
    for k, (start, label) in enumerate(zip(starts, labels, strict=True)):
        stop = min(starts[k + 1], n_commands) if k + 1 < len(starts) else n_commands
        if stop > start:
            blocks.append({"start": start, "stop": stop, "label": label,
                           "fault": label not in ("normal", "repair")})
    return blocks


def _short_label(entry):
    """A schedule entry without its step and with short numbers: ``5:deform_limb:j:0.1:0.7853981633974483``
    -> ``deform_limb:j:0.1:0.785``."""
    tokens = entry.split(":")
    if tokens[0].isdigit():
        tokens = tokens[1:]
    out = []
    for token in tokens:
        try:
            out.append(token if token.lstrip("-").isdigit() else f"{float(token):.3g}")
        except ValueError:
            out.append(token)
    return ":".join(out)


def build_report(result, bag, part=None):
    """The JSON-serialisable report of a replay (``part``: end effector; default :func:`default_part`)."""
    learner = result.learner
    final = learner.edge_status()
    if part is None and final:
        part = default_part([(e["parent"], e["child"]) for e in final], learner.root)
    steps = []
    for record in result.steps:
        error = record["prediction"].get(part)
        steps.append({key: value for key, value in record.items() if key != "prediction"} | {
            "end_effector": None if error is None else {"trans_error": error[0], "rot_error": error[1]}})
    blocks = fault_blocks(result.info, result.n_commands)
    for block in blocks:
        errors = [s["end_effector"]["trans_error"] for s in steps
                  if block["start"] <= s["command_index"] < block["stop"] and s["end_effector"] is not None]
        block["mean_end_effector_error"] = float(np.mean(errors)) if errors else None
        block["n_predicted"] = len(errors)
    settings = dataclasses.asdict(result.settings)
    report = {
        "bag": str(bag), "session": result.info, "settings": settings, "end_effector": part,
        "n_commands": result.n_commands, "n_steps": len(steps), "seconds": result.seconds,
        "steps_per_second": len(steps) / result.seconds if result.seconds > 0 else None,
        "rejected": dict(sorted(result.rejected.items())),
        "corrected": dict(sorted(learner.corrected.items())),
        "imported": None if result.imported is None else dict(sorted(result.imported.items())),
        "steps": steps,
        "events": [event.to_dict() for event in result.events],
        "final": {"phase": learner.phase, "step": learner.step, "root": learner.root,
                  "edges": [{k: e[k] for k in ("parent", "child", "model", "kind", "actions", "valid", "trans_error",
                                               "rot_error")} for e in final]},
        "blocks": blocks,
    }
    return _json_safe(report)


def _json_safe(value):
    """Replace NaN and inf (not JSON) by None and numpy scalars by Python ones, recursively."""
    if isinstance(value, dict):
        return {str(k): _json_safe(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_json_safe(v) for v in value]
    if isinstance(value, (np.integer, np.bool_)):
        return value.item()
    if isinstance(value, (float, np.floating)):
        return float(value) if math.isfinite(value) else None
    return value


def format_timeline(report, width=116):
    """The events as a text timeline (one line per decision, wrapped), with the session's faults in between."""
    faults = [(b["start"], b["label"]) for b in report["blocks"] if b["start"] > 0]
    lines = [f"Timeline of the learner's decisions replaying {report['bag']}"]
    # A fault is listed before the events of its step (stable sort: events keep their order).
    ordered = sorted([{"step": s, "kind": None, "reason": label} for s, label in faults] + report["events"],
                     key=lambda e: e["step"])
    for event in ordered:
        if event["kind"] is None:
            lines.append(f"  ---- step {event['step']}: {event['reason']} ----")
            continue
        reason = event["reason"]
        if event["kind"] in ("structure_changed", "structure_found") and len(reason) > 150:
            reason = reason[:147] + "..."
        wrapped = textwrap.wrap(reason, width - 28) or [""]
        lines.append(f"  {event['step']:4d}  {event['kind']:19s}  {wrapped[0]}")
        lines += [f"  {'':4s}  {'':19s}  {line}" for line in wrapped[1:]]
    return "\n".join(lines) + "\n"


def format_summary(report):
    """Final structure, event counts, rejected inputs and the end effector's mean error per fault block."""
    info = report["session"] or {}
    final = report["final"]
    rate = report["steps_per_second"]
    lines = [f"replayed {report['bag']} ({info.get('robot', 'unknown robot')}, protocol "
             f"{info.get('protocol', 'unknown')}): {report['n_commands']} commands, {report['n_steps']} learning "
             f"steps in {report['seconds']:.1f} s" + (f" ({rate:.0f} steps/s)" if rate else "")]
    lines.append(f"final body scheme (phase {final['phase']}, root {final['root']}):")
    if not final["edges"]:
        lines.append("  none: no valid spanning tree was found")
    for e in final["edges"]:
        trans = "-" if e["trans_error"] is None else f"{1000 * e['trans_error']:.0f} mm"
        lines.append(f"  {e['parent']}-{e['child']}  {e['model']:24s} {trans:>8s}  "
                     f"{'valid' if e['valid'] else 'INVALID'}")
    counts = Counter(event["kind"] for event in report["events"])
    lines.append("events: " + (", ".join(f"{kind} {n}" for kind, n in counts.items()) or "none"))
    if report.get("imported") is not None:
        lines.append("imported: " + ", ".join(f"{k} {n}" for k, n in report["imported"].items()))
    rejected = report["rejected"]
    lines.append("rejected inputs: " + (", ".join(f"{k} {n}" for k, n in rejected.items()) or "none"))
    if report.get("corrected"):
        lines.append("corrected inputs: " + ", ".join(f"{k} {n}" for k, n in report["corrected"].items()))
    part = report["end_effector"]
    if part is None:
        lines.append("end effector: none (no body scheme)")
        return "\n".join(lines) + "\n"
    lines.append(f"end effector (part {part}) mean prediction error per block (predicted before each step):")
    for block in report["blocks"]:
        mean = block["mean_end_effector_error"]
        text = "no prediction" if mean is None else f"{1000 * mean:5.0f} mm over {block['n_predicted']} steps"
        lines.append(f"  steps {block['start']:4d}-{block['stop'] - 1:4d}  {block['label']:28s} {text}")
    return "\n".join(lines) + "\n"


def plot_errors(report, path):
    """Write ``errors.png``: per-edge test-window errors and the end-effector error over time, faults shaded."""
    from matplotlib.figure import Figure

    steps = report["steps"]
    x = np.array([s["step"] for s in steps])
    final = [(e["parent"], e["child"]) for e in report["final"]["edges"]]
    pairs = sorted({tuple(sorted((e["parent"], e["child"]))) for s in steps for e in s["edges"]})
    fig = Figure(figsize=(11, 8.5), layout="constrained")
    axes = fig.subplots(3, 1, sharex=True)
    for pair in sorted(pairs, key=lambda p: tuple(sorted(p)) in {tuple(sorted(f)) for f in final}):
        trans = np.full(len(steps), np.nan)
        rot = np.full(len(steps), np.nan)
        for k, s in enumerate(steps):
            for e in s["edges"]:
                if tuple(sorted((e["parent"], e["child"]))) == pair:
                    trans[k] = np.nan if e["trans_error"] is None else 1000 * e["trans_error"]
                    rot[k] = np.nan if e["rot_error"] is None else math.degrees(e["rot_error"])
        in_final = next((f for f in final if tuple(sorted(f)) == pair), None)
        # Edges of the final tree in colour; edges that were only briefly in the tree (bootstrapping) in grey.
        style = {"lw": 1, "label": f"{in_final[0]}-{in_final[1]}"} if in_final else {"lw": 0.6, "color": "0.7"}
        axes[0].plot(x, trans, **style)
        axes[1].plot(x, rot, **style)
    config = report["settings"]["config"]
    if config.get("theta_trans"):
        axes[0].axhline(1000 * config["theta_trans"], color="gray", lw=0.8, ls=":", label="threshold")
    if config.get("theta_rot"):
        axes[1].axhline(math.degrees(config["theta_rot"]), color="gray", lw=0.8, ls=":", label="threshold")
    axes[0].set_ylabel("edge trans. error [mm]")
    axes[1].set_ylabel("edge rot. error [deg]")
    part = report["end_effector"]
    ee = np.array([np.nan if s["end_effector"] is None or s["end_effector"]["trans_error"] is None
                   else 1000 * s["end_effector"]["trans_error"] for s in steps])
    axes[2].plot(x, ee, color="0.6", lw=0.7, label=f"part {part}, per step")
    window = report["settings"]["config"]["test_window"]
    if ee.size >= window:
        # Mean over the last test_window steps, ignoring steps without a prediction.
        valid = np.isfinite(ee)
        sums = np.convolve(np.where(valid, ee, 0.0), np.ones(window), mode="full")[:ee.size]
        counts = np.convolve(valid.astype(float), np.ones(window), mode="full")[:ee.size]
        mean = np.where(counts > 0, sums / np.maximum(counts, 1), np.nan)
        axes[2].plot(x, mean, color="black", lw=1.3, label=f"mean of last {window}")
    axes[2].set_ylabel("end-effector error [mm]")
    axes[2].set_xlabel("step")
    step_of_command = {s["command_index"]: s["step"] for s in steps}
    for block in report["blocks"]:
        if block["fault"]:
            start = step_of_command.get(block["start"], block["start"])
            stop = step_of_command.get(block["stop"] - 1, block["stop"] - 1) + 1
            for ax in axes:
                ax.axvspan(start, stop, color="tab:orange", alpha=0.12, lw=0)
            axes[0].text(start, 1.0, f" {block['label']}", transform=axes[0].get_xaxis_transform(), va="bottom",
                         fontsize=7)
    for event in report["events"]:
        style = _MARKED_EVENTS.get(event["kind"])
        if style:
            for ax in axes:
                ax.axvline(event["step"], color=style[0], ls=style[1], lw=0.8, alpha=0.7)
    for kind, (color, style) in _MARKED_EVENTS.items():
        axes[2].plot([], [], color=color, ls=style, lw=0.8, label=kind)
    for ax in axes:
        ax.grid(alpha=0.3)
    axes[0].legend(fontsize=7, ncol=4, loc="upper right", title="final tree edges (grey: earlier ones)",
                   title_fontsize=7)
    axes[2].legend(fontsize=7, ncol=3, loc="upper right")
    fig.suptitle(f"Replay of {pathlib.Path(report['bag']).name}: test-window errors of the tree edges and "
                 "end-effector prediction error (shaded: fault)", fontsize=10)
    fig.savefig(path, dpi=110)


# ---------------------------------------------------------------------- command line
def parser():
    """The command-line interface."""
    p = argparse.ArgumentParser(prog="replay_offline", description=__doc__.split("\n\n")[0])
    p.add_argument("bag", help="session bag (rosbag2 directory), or with --source-map another stack's bag or a table "
                               "(.csv, .jsonl)")
    p.add_argument("--source-map", default=None,
                   help="YAML mapping another stack's topics and frames to joints and bodies (docs/your-data.md)")
    p.add_argument("--params", default=None,
                   help="scheme_node parameter file (default: the shipped config/scheme_node.yaml)")
    p.add_argument("--out", default=None, help="output directory (default: out/replay/<bag name>)")
    p.add_argument("--part", type=int, default=None,
                   help="end-effector part id (default: the part farthest from the root in the final tree)")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    return p


@command
def main(argv=None):
    """Replay a bag offline and write the report; returns the exit code (0 ok, 1 error)."""
    args = parser().parse_args(argv)
    bag = pathlib.Path(args.bag)
    out = pathlib.Path(args.out) if args.out else pathlib.Path("out") / "replay" / bag.name
    params = pathlib.Path(args.params) if args.params else default_params_file()
    try:
        settings = SchemeSettings.from_yaml(params)
        source_map = SourceMap.from_yaml(args.source_map) if args.source_map else None
        n_commands = bag_topics(bag).get(COMMANDS, (None, 0))[1] if source_map is None else None
        with tqdm(total=n_commands, desc=f"replaying {bag.name}", unit="step", disable=args.quiet) as bar:
            result = replay_bag(bag, settings, progress=lambda done: bar.update(done - bar.n), source_map=source_map)
        if not result.steps:
            imported = f"; imported: {dict(result.imported)}" if result.imported is not None else ""
            raise BodySchemeError(f"no command was paired with an observation (rejected: {dict(result.rejected)}"
                                  f"{imported}); check the pairing parameters in the parameter file"
                                  f"{' and the source map' if imported else ''}")
        if args.part is not None and args.part not in result.learner.part_ids:
            raise BodySchemeError(f"--part {args.part} is not a part: {list(result.learner.part_ids)}")
        report = build_report(result, bag, part=args.part)
        out.mkdir(parents=True, exist_ok=True)
        (out / "report.json").write_text(json.dumps(report, indent=1, allow_nan=False))
        (out / "events.txt").write_text(format_timeline(report))
        plot_errors(report, out / "errors.png")
    except (BodySchemeError, OSError) as error:
        print(f"replay_offline: {error}", file=sys.stderr)
        return 1
    print(format_summary(report), end="")
    print(f"wrote {out / 'report.json'}, {out / 'events.txt'}, {out / 'errors.png'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
