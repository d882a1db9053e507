"""Figures the README and the model card quote from docs/accuracy.md are its figures."""

from __future__ import annotations

import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
DOCS = ROOT / "docs"


def _accuracy_md() -> dict[tuple[str, str, str, str], float]:
    """(lab, protocol, method, input) -> top-1 of docs/accuracy.md."""
    out = {}
    for line in (DOCS / "accuracy.md").read_text().splitlines():
        cells = [c.strip() for c in line.strip().strip("|").split("|")]
        if len(cells) == 9 and cells[1] in ("pairs", "panel"):
            out[tuple(cells[:4])] = float(cells[4])
    return out


def _number(cell: str) -> float:
    return float(cell.replace("*", "").strip())


def test_readme_results_table_matches_accuracy_md():
    """README's Results table is accuracy.md's: its CPD column kept the figures from before
    session 33's rerun (NP 30.5, EY 14.2, SF 33.6 for 30.4, 14.1, 34.0)."""
    acc = _accuracy_md()
    columns = [("pairs", "fdlc", "colour"), ("pairs", "floor", "colour"), ("pairs", "fdlc", "position"),
               ("pairs", "CPD", "position"), ("panel", "fdlc", "colour"), ("panel", "fdlc", "colour, lab handedness")]
    readme = (ROOT / "README.md").read_text().splitlines()
    start = next(i for i, line in enumerate(readme) if line.startswith("| lab | pairs: fdlc + colour"))
    mismatches, rows = [], 0
    for line in readme[start + 2:]:
        if not line.startswith("|"):
            break
        cells = [c.strip() for c in line.strip().strip("|").split("|")]
        lab, values = cells[0], [_number(c) for c in cells[1:]]
        rows += 1
        for (protocol, method, given), value in zip(columns, values):
            doc = acc[(lab, protocol, method, given)]
            if value != doc:
                mismatches.append(f"{lab} {protocol} {method} {given}: README {value}, accuracy.md {doc}")
    assert rows == 5
    assert not mismatches, "; ".join(mismatches)


def test_model_card_cpd_range_matches_accuracy_md():
    """The model card's CPD range is accuracy.md's (it kept 11.1-33.6 after SF's 34.0)."""
    acc = _accuracy_md()
    cpd = [v for (lab, protocol, method, given), v in acc.items() if method == "CPD"]
    card = (DOCS / "model_card.md").read_text()
    found = re.search(r"CPD\s+(\d+\.\d)–(\d+\.\d)\s*%", card)
    assert found, "the model card's CPD range is gone"
    assert (float(found.group(1)), float(found.group(2))) == (min(cpd), max(cpd))
