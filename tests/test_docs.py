"""Figures the README and the model card quote from docs/accuracy.md are its figures; the
dependencies the README lists are the ones the core imports."""

from __future__ import annotations

import ast
import re
import subprocess
import sys
import textwrap
import tomllib
from importlib.metadata import packages_distributions
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


PACKAGE = ROOT / "src" / "napari_fdlc"


OPTIONAL_IN_CORE = {"matplotlib"}


def _core_third_party_imports() -> dict[str, set[str]]:
    """Top-level third-party modules imported anywhere in the core (not ``_napari``)."""
    found: dict[str, set[str]] = {}
    for path in PACKAGE.rglob("*.py"):
        if "_napari" in path.parts:
            continue
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            names = []
            if isinstance(node, ast.Import):
                names = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
                names = [node.module]
            for name in names:
                top = name.split(".")[0]
                if top not in sys.stdlib_module_names and top != "napari_fdlc":
                    found.setdefault(top, set()).add(path.name)
    return found


def _declared(requirements: list[str]) -> set[str]:
    return {re.split(r"[<>=!~ \[;]", r)[0].strip().lower().replace("_", "-") for r in requirements}


def test_every_package_the_core_imports_is_a_declared_and_pinned_dependency():
    """Every third-party module the core (everything outside ``_napari``) imports is a core
    dependency in pyproject.toml and pinned in constraints.txt, as README's dependency table
    promises ("Versions are pinned in constraints.txt"; segmentation: "scikit-image was not
    needed"). Instead segment.py imports skimage (h_maxima, watershed), which neither
    pyproject.toml's dependencies nor constraints.txt name and README says is not used."""
    project = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    core = _declared(project["dependencies"])
    pinned = _declared([line for line in (ROOT / "constraints.txt").read_text().splitlines()
                        if line.strip() and not line.startswith("#")])
    dists = packages_distributions()
    undeclared, unpinned = [], []
    for module, files in sorted(_core_third_party_imports().items()):
        if module in OPTIONAL_IN_CORE:
            continue
        names = [d.lower().replace("_", "-") for d in dists.get(module, [module])]
        if not any(n in core for n in names):
            undeclared.append(f"{module} ({'/'.join(names)}) imported by {', '.join(sorted(files))}")
        if not any(n in pinned for n in names):
            unpinned.append(module)
    readme = (ROOT / "README.md").read_text()
    assert not undeclared, ("not in pyproject.toml's dependencies: " + "; ".join(undeclared)
                            + (" -- and README says 'scikit-image was not needed'"
                               if "scikit-image was not needed" in readme else ""))
    assert not unpinned, f"not pinned in constraints.txt: {unpinned}"


def test_fdlc_segment_of_a_clipped_stack_works_on_a_core_install(tmp_path):
    """`fdlc segment` (README's first command line) on a stack whose brightest nucleus is
    clipped (a 12-bit camera over range, common in real recordings) works with the core
    dependencies alone: one nucleus found, exit 0. Instead, without scikit-image (not a core
    dependency; it only comes with napari), it dies with a ModuleNotFoundError traceback from
    segment._one_per_saturated_nucleus."""
    script = textwrap.dedent("""
        import sys
        sys.modules["skimage"] = None  # a core install: pyproject.toml's dependencies only
        import numpy as np
        from scipy import ndimage
        from napari_fdlc.io.images import Stack, write_tiff
        z, y, x = np.mgrid[:16, :64, :64]
        r = np.sqrt(((z - 8) * 1.0) ** 2 + ((y - 32) * 0.25) ** 2 + ((x - 32) * 0.25) ** 2)
        blob = ndimage.gaussian_filter((r <= 1.5).astype(float), (0.7, 0.6, 0.6))
        blob /= blob.max()
        noise = np.random.default_rng(0).normal(0, 1, blob.shape)
        volume = np.minimum(100 + 20000 * blob + noise, 4095).astype(np.uint16)  # clipped at 4095
        write_tiff(sys.argv[1], Stack(volume[None], (1.0, 0.25, 0.25), ["W"]))
        from napari_fdlc.cli import main
        sys.exit(main(["segment", sys.argv[1], "--out", sys.argv[2], "--quiet"]))
    """)
    out = tmp_path / "neurons.csv"
    proc = subprocess.run([sys.executable, "-c", script, str(tmp_path / "clipped.ome.tif"), str(out)],
                          capture_output=True, text=True, timeout=120,
                          env={"OMP_NUM_THREADS": "1", "PATH": "/usr/bin:/bin"})
    assert "Traceback" not in proc.stderr, proc.stderr[-600:]
    assert proc.returncode == 0, proc.stderr
    assert len(out.read_text().strip().splitlines()) == 2  # header + one nucleus
