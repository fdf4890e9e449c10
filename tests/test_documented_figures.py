"""Every figure docs/figures.yaml registers is quoted in its doc as its source last measured it.

An entry names a doc, a ``quote`` (its text with ``{}`` where the figures stand; line breaks and spaces match any
whitespace, as Markdown wraps lines), and per ``{}`` a key of the source JSON (``docs/results/results.json`` from
``make experiments``, ``docs/results/bench.json`` and ``sim.json`` from ``make bench``), ``"key * 100"`` for a
fraction quoted in %, ``a.b`` for key ``b`` of the object at key ``a``.
A quoted figure ``q`` of a key whose value is ``v`` passes when ``|q - scale * v|`` is within the largest of: half a
unit of the last digit quoted (rounding), the key's own std (``<key>_std`` in the source, times ``scale``) and the
entry's ``rel`` times ``|scale * v|`` (timings, which vary from run to run on one machine). Regenerating a source
and not the text fails here, naming both."""

from __future__ import annotations

import json
import re

import pytest
import yaml
from workspace import REPO

NUMBER = r"(-?\d+(?:\.\d+)?)"
ENTRIES = yaml.safe_load((REPO / "docs" / "figures.yaml").read_text())


def quote_pattern(quote):
    """The regular expression of a quote: its literal text, any whitespace for a space, a number for each ``{}``."""
    pieces = ["".join(r"\s+" if token.isspace() else re.escape(token) for token in re.split(r"(\s+)", piece))
              for piece in quote.split("{}")]
    return re.compile(NUMBER.join(pieces))


def tolerance(quoted, value, std, rel):
    """How far a quoted figure may be from ``value``: rounding of its last digit, the std, a relative share."""
    decimals = len(quoted.partition(".")[2])
    return max(0.5 * 10.0 ** -decimals, std, rel * abs(value))


def lookup(source, key):
    """The value at ``key``, else at the rest of ``key`` in the object at its part before a dot (a key may hold a
    dot: ``perception_640x480_tag_1.5m_depth_mm``); None when there is neither."""
    if not isinstance(source, dict):
        return None
    if key in source:
        return source[key]
    head, dot, rest = key.partition(".")
    return lookup(source.get(head), rest) if dot else None


def figure_problems(entry, text, source):
    """The entry's quoted figures that differ from their source, as sentences (empty when every one agrees)."""
    matches = quote_pattern(entry["quote"]).findall(text)
    if len(matches) != 1:
        return [f"the quote {entry['quote']!r} is found {len(matches)} times (once expected): edit docs/figures.yaml "
                f"with the text"]
    found = matches[0] if isinstance(matches[0], tuple) else (matches[0],)
    keys, rel = entry["keys"], float(entry.get("rel", 0.0))
    if len(found) != len(keys):
        return [f"the quote {entry['quote']!r} has {len(found)} figures and {len(keys)} keys"]
    problems = []
    for quoted, item in zip(found, keys, strict=True):
        key, _, factor = item.partition("*")
        key, scale = key.strip(), float(factor or 1.0)
        if lookup(source, key) is None:
            problems.append(f"{key} is not in {entry['source']}")
            continue
        value = scale * float(lookup(source, key))
        std = scale * float(lookup(source, f"{key}_std") or 0.0)
        if abs(float(quoted) - value) > tolerance(quoted, value, std, rel):
            problems.append(f"{entry['in']} quotes {quoted} for {key}, {entry['source']} has {value:.4g} "
                            f"(std {std:.2g}, rel {rel:g}) in {entry['quote']!r}")
    return problems


@pytest.mark.parametrize("entry", ENTRIES, ids=[f"{e['in']}: {e['quote'][:50]}" for e in ENTRIES])
def test_a_documented_figure_is_its_sources(entry):
    text = (REPO / entry["in"]).read_text()
    source = json.loads((REPO / entry["source"]).read_text())
    assert figure_problems(entry, text, source) == []


def test_the_check_catches_a_stale_figure_and_a_lost_quote():
    """Rounding and the std are allowed, a figure beyond both is named, a quote the text lost is reported."""
    entry = {"in": "doc.md", "source": "r.json", "quote": "found in {} % of the runs, {} mm", "keys": ["a * 100", "b"]}
    source = {"a": 0.955, "b": 1.23, "b_std": 0.01}
    assert figure_problems(entry, "found in\n95.5 % of the runs, 1.2 mm", source) == []
    assert figure_problems(entry, "found in 96 % of the runs, 1.2 mm", source) == []
    problems = figure_problems(entry, "found in 97 % of the runs, 1.2 mm", source)
    assert len(problems) == 1 and "quotes 97 for a" in problems[0]
    assert figure_problems(entry, "found in 95.5 % of runs, 1.2 mm", source)[0].startswith("the quote")
    assert figure_problems({**entry, "rel": 0.05}, "found in 100 % of the runs, 1.2 mm", source) == []
    nested = {**entry, "keys": ["rates.a * 100", "rates.c"]}
    assert figure_problems(nested, "found in 95.5 % of the runs, 1.2 mm", {"rates": source}) == \
        ["rates.c is not in r.json"]
    dotted = {**entry, "keys": ["a * 100", "b_1.5m"]}  # a key with a dot of its own
    assert figure_problems(dotted, "found in 95.5 % of the runs, 1.2 mm", {"a": 0.955, "b_1.5m": 1.23}) == []
