"""``fdlc label`` as a function: validate every input, load the model once, write atomically.

The output layout is the public contract of ``../shared/docs/neuron_table.md``: one row per test neuron in
input order, ``neuron_index, x_um, y_um, z_um, auto_id, auto_conf, cand_1, prob_1, … cand_K,
prob_K`` (K = max(top_k, 3)), then the test's other columns (its ``label`` is not copied).
"""

from __future__ import annotations

import os
import re
from pathlib import Path

import numpy as np
import pandas as pd

from .errors import FdlcError, check_output, warn
from .geometry import refuse_flat
from .identify import (ADAPT_MIN_TESTS, FEW_NEURONS, Identifier, can_adapt_colours, colour_note, default_identifier,
                       harmonise, label_neurons, shipped_weights, smaller_worm_note)
from .match import Labelling, make_labelling, name_probabilities
from .table import COORDS, NeuronTable, read_volume, warn_implausible_scales, write_table


# Columns of an earlier ``fdlc label`` output: labelling that output again must not carry its
# old answer (e.g. a stale cand_4 after --top-k 3) beside the new one.
_OUTPUT_COLUMNS = re.compile(r"neuron_index|auto_id|auto_conf|(cand|prob)_\d+")


MAX_TOP_K = 1000


def _six_decimals(p: np.ndarray) -> np.ndarray:
    """Probabilities to 6 decimals, rounded down, so that a row's written candidates still sum
    to at most 1 (each rounded to nearest, 0.9999906 + 2 × 0.0000047 was written as 1.000001);
    a hair (1e-12) is added first so that an exact 0.3, stored as 0.29999…, stays 0.3."""
    return np.floor(np.asarray(p, float) * 1e6 + 1e-6) / 1e6


def labelling_frame(test: NeuronTable, result: Labelling, top_k: int = 3) -> pd.DataFrame:
    k = max(top_k, 3)
    cand, cand_p = result.candidates(k)
    columns = {"neuron_index": np.arange(len(test))}
    columns.update({c: test.xyz[:, i] for i, c in enumerate(COORDS)})
    columns["auto_id"] = result.auto_id
    columns["auto_conf"] = _six_decimals(result.auto_conf)
    for r in range(k):
        written = _six_decimals(cand_p[:, r])
        # a name whose probability is written as 0 is no candidate (empty / 0, as top_k's own)
        columns[f"cand_{r + 1}"] = [row[r] if p > 0 else "" for row, p in zip(cand, written)]
        columns[f"prob_{r + 1}"] = written
    # The test's other columns as they were written (text read from a file), not as parsed.
    given = test.text if test.text is not None else test.to_dataframe()
    for c in given.columns:
        if c not in columns and c not in COORDS and c != "label" and not _OUTPUT_COLUMNS.fullmatch(c):
            columns[c] = given[c].to_numpy()
    return pd.DataFrame(columns)


def _output_paths(tests: list[str], out: str, inputs: list[str]) -> list[Path]:
    """Where each test's answer goes, refused before any work when it cannot be written there
    or would replace one of the ``inputs``."""
    if not out:
        raise FdlcError("--out is empty: give an output file (one test) or folder (several tests)")
    stems = [Path(t).stem for t in tests]
    seen = set()
    for stem in stems:
        if stem in seen:
            raise FdlcError(f"two test tables share the file stem '{stem}': their outputs would collide in {out}")
        seen.add(stem)
    out_path = Path(out)
    as_folder = len(tests) > 1 or out_path.is_dir() or out.endswith(("/", os.sep))
    if as_folder and out_path.exists() and not out_path.is_dir():
        raise FdlcError(f"{out}: with several test tables --out must be a directory")
    if not as_folder:  # its folder is created as segment's and track's are (a fresh results path)
        return [check_output(out, inputs, create_folder=True)]
    return [check_output(out_path / f"{stem}.csv", inputs, create_folder=True) for stem in stems]


def label_files(
    tests: list[str],
    templates: list[str] | None = None,
    out: str = "labels.csv",
    use_colour: bool = True,
    top_k: int = 3,
    method: str = "fdlc",
    weights: str | None = None,
    chirality: str = "auto",
    shared_handedness: bool | None = None,
    use_atlas: bool = True,
    adapt_colours: bool | None = None,
) -> list[Path]:
    """Label each test table and write one CSV per test. Returns the paths written.
    ``shared_handedness``: the panel names the tests in one handedness when they clearly agree
    (:meth:`Identifier.label_panel_many`; None: wherever it applies, i.e. several tests, the
    panel, ``auto``); ``adapt_colours``: the panel's colours are measured
    on the tests themselves, then they are named again (same method; None: wherever it applies,
    i.e. the panel with colour in at least ``ADAPT_MIN_TESTS`` tests); ``use_atlas``: with
    templates, join the built-in atlas's own answer (:func:`napari_fdlc.identify.label_neurons`)."""
    if not tests:
        raise FdlcError("no test table given" + (": list the test tables before --template, which reads every table "
                                                 "after it" if templates else ""))
    if not 1 <= top_k <= MAX_TOP_K:  # (the atlas knows ~180 names; 10**20 ran the model, then overflowed)
        raise FdlcError(f"--top-k must be from 1 to {MAX_TOP_K} (got {top_k})")
    if method not in ("fdlc", "cpd"):
        raise FdlcError(f"unknown --method '{method}' (use fdlc or cpd)")
    if method == "cpd" and not templates:
        raise FdlcError("--method cpd needs --template (the reference panel is for the fdlc model)")
    # Validate everything before any work or any write.
    one_volume = "fdlc label names one volume: give one time point, or follow them all with fdlc track --reference"
    test_tables = [read_volume(t, one_volume, names=False) for t in tests]  # a test's names are not used
    template_tables = [read_volume(t, one_volume) for t in (templates or [])]
    for t in template_tables:
        if not t.named.any():
            raise FdlcError(f"{t.source}: the template has no named neuron (a 'label' column with names is needed)")
    from .errors import model_files
    from .reference import shipped_atlas_path

    # The weights (the shipped ones by default) and the shipped atlas are read too, never written;
    # checked before any warning (a refusal is one line)
    paths = _output_paths(tests, out, [*tests, *(templates or []), *model_files(weights or shipped_weights()),
                                       shipped_atlas_path()])
    if method == "fdlc":  # once for all the tests
        template_tables = harmonise(template_tables)
    warn_implausible_scales([*test_tables, *template_tables])
    for t in test_tables:
        if len(t) < FEW_NEURONS:
            warn(f"{t.source}: only {len(t)} neuron(s): names from so few positions are guesses, confidences too")
    if method == "cpd":
        ignored = [option for option, given in (("--chirality", chirality != "auto"), ("--no-atlas", not use_atlas),
                                                ("--weights", weights is not None)) if given]
        if ignored:
            warn(f"{' and '.join(ignored)} {'is' if len(ignored) == 1 else 'are'} for the fdlc method "
                 "(cpd tries both handednesses, with no model): ignored here")
    elif not use_atlas and not template_tables:
        warn("--no-atlas is for --template (the built-in panel always joins the atlas's answer): ignored here")
    applies = not template_tables and chirality == "auto"
    if shared_handedness and not (applies and len(test_tables) > 1):
        warn("--shared-handedness is for several tests named by the built-in panel with --chirality auto: ignored here")
    shared_handedness = applies and len(test_tables) > 1 and shared_handedness is not False
    adapts = not template_tables and can_adapt_colours(test_tables, use_colour)
    if adapt_colours and not adapts:
        warn(f"--adapt-colours is for the built-in panel with colour (R, G, B) in at least {ADAPT_MIN_TESTS} recordings "
             f"(copies and tests of fewer than {FEW_NEURONS} neurons not counted): ignored here")
    adapt_colours = adapts and adapt_colours is not False
    if method == "fdlc":
        from .reference import load_panel

        references = template_tables or load_panel().templates
        for t in test_tables:
            note = colour_note(t, references, use_colour)
            if note:
                warn(note)
        identifier = (Identifier.load(weights, identifies=True) if weights else default_identifier()).with_chirality(chirality)
        if template_tables or not (shared_handedness or adapt_colours):
            results = [label_neurons(t, template_tables or None, use_colour, identifier=identifier, use_atlas=use_atlas)
                       for t in test_tables]
        else:
            results = identifier.label_panel_many(test_tables, load_panel(), use_colour, share_handedness=shared_handedness,
                                                  adapt_colours=adapt_colours)
            batch = results[0].info.get("batch_handedness") or {}
            if batch.get("decided"):
                warn(f"{batch['lean_mirrored']} of the {batch['votes']} recordings (of {batch['tests']}) whose model and "
                     f"registration agree lean mirrored relative to the atlas: all are named as '{batch['decided']}' "
                     "(--chirality decides yourself; --no-shared-handedness lets each recording decide alone)")
    else:
        results = [cpd_labelling(t, template_tables, use_colour) for t in test_tables]
        if use_colour and any(t.colours for t in test_tables):
            warn("--method cpd names by position only: the colour columns are not used")
    frames = []  # every answer made before any is written: a failure leaves no output behind
    for test, result in zip(test_tables, results):
        note = smaller_worm_note(test, result)
        if note:
            warn(note)
        kept = result.info.get("head_window")
        if kept is not None:
            warn(f"{test.source}: {len(test) - kept} neuron(s) lie beyond the head (the view reaches into the body): "
                 "they get no name")
        frames.append(labelling_frame(test, result, top_k))
    for frame, path in zip(frames, paths):
        write_table(frame, path)
    return paths


def cpd_labelling(test: NeuronTable, templates: list[NeuronTable], use_colour: bool = False) -> Labelling:
    from .baselines import cpd_match

    refuse_flat(test.xyz, test.source, FEW_NEURONS)  # as the model's path: left cannot be told from right
    per_template = [(cpd_match(t, test, use_colour)[:, :-1], t.labels) for t in templates]
    names, probs = name_probabilities(per_template)
    return make_labelling(names, probs, info={"method": "cpd"})
