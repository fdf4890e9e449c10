"""What every benchmark command does with its figures: print the table, write the JSON file the issues' keys are in."""

from __future__ import annotations

import json
import os

__all__ = ["report"]


def report(result, table, path):
    """Print ``table`` and write ``result`` as JSON to ``path`` (directories are created); returns 0."""
    print(table)
    os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
    with open(path, "w", encoding="utf-8") as f:
        json.dump(result, f, indent=2)
        f.write("\n")
    print(f"wrote {path}")
    return 0
