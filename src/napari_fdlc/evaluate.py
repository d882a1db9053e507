"""Accuracy, calibration and coverage of any matcher on annotated worms.

Accuracy follows the fDLC paper: the fraction of labelled test neurons whose name also exists
in the template (or the panel) that are given that name by the one-to-one assignment (top-1),
or whose name is among the three most likely candidates (top-3).

Protocols:
* ``pairs`` — within one lab, each worm is the template for the others;
* ``panel`` — no template: the built-in reference panel (an atlas built without the lab).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .errors import FdlcError
from .match import Labelling, make_labelling, name_probabilities
from .table import NeuronTable, check_named


@dataclass
class Scores:
    correct: list = field(default_factory=list)  # top-1 hit per scored neuron
    top3: list = field(default_factory=list)
    # auto_conf as the contract gives it: of the name, or for a neuron left unnamed of "no named
    # match" — wrong for a scored neuron (its truth is named), however sure; a stand-in 0 made
    # a confident wrong "no match" count as perfectly calibrated
    conf: list = field(default_factory=list)
    named: list = field(default_factory=list)  # a name given (the slider shows only these)
    seconds: list = field(default_factory=list)  # per test volume

    def add(self, result: Labelling, test: NeuronTable, vocabulary: set[str], seconds: float | None = None) -> None:
        cand, _ = result.candidates(3)
        for j, truth in enumerate(test.labels):
            if truth and truth in vocabulary:
                self.correct.append(result.auto_id[j] == truth)
                self.top3.append(truth in cand[j])
                self.conf.append(float(result.auto_conf[j]))
                self.named.append(bool(result.auto_id[j]))
        if seconds is not None:
            self.seconds.append(seconds)

    def merge(self, other: "Scores") -> None:
        for name in ("correct", "top3", "conf", "named", "seconds"):
            getattr(self, name).extend(getattr(other, name))

    def summary(self) -> dict:
        c = np.asarray(self.correct, float)
        return {
            "top1": float(c.mean()) if len(c) else float("nan"),
            "top3": float(np.mean(self.top3)) if len(c) else float("nan"),
            "n": int(len(c)),
            "ece": expected_calibration_error(np.asarray(self.conf), c),
            "ms_per_volume": 1000 * float(np.median(self.seconds)) if self.seconds else float("nan"),
        }


def expected_calibration_error(conf: np.ndarray, correct: np.ndarray, bins: int = 10) -> float:
    """Mean |accuracy - confidence| over equal-width confidence bins, weighted by bin size."""
    if len(conf) == 0:
        return float("nan")
    idx = _bin_of(conf, bins)
    ece = 0.0
    for b in range(bins):
        mask = idx == b
        if mask.any():
            ece += mask.mean() * abs(correct[mask].mean() - conf[mask].mean())
    return float(ece)


def reliability(conf: np.ndarray, correct: np.ndarray, bins: int = 10) -> list[tuple[float, float, int]]:
    """(mean confidence, accuracy, count) per confidence bin."""
    idx = _bin_of(conf, bins)
    return [(float(conf[idx == b].mean()), float(correct[idx == b].mean()), int((idx == b).sum()))
            for b in range(bins) if (idx == b).any()]


def _bin_of(conf: np.ndarray, bins: int) -> np.ndarray:
    """Each confidence's bin, [k / bins, (k + 1) / bins), the last closed: a confidence on an edge
    goes to the bin above (np.linspace's 0.30000000000000004 put 0.3 in the one below)."""
    return np.clip(np.floor(np.asarray(conf, float) * bins).astype(int), 0, bins - 1)


def coverage_curve(conf: np.ndarray, correct: np.ndarray, named: np.ndarray | None = None,
                   thresholds=(0.0, 0.05, 0.1, 0.2, 0.3, 0.5, 0.7, 0.9, 0.99)):
    """(threshold, coverage, accuracy of the labels kept) for the confidence slider: a label is
    kept when a name was given (``named``; default all) at ``auto_conf`` ≥ the threshold."""
    out = []
    if len(conf) == 0:  # nothing scored (a lab of one worm has no pair)
        return [(t, float("nan"), float("nan")) for t in thresholds]
    named = np.ones(len(conf), bool) if named is None else np.asarray(named, bool)
    for t in thresholds:
        kept = named & (conf >= t)
        out.append((t, float(kept.mean()), float(correct[kept].mean()) if kept.any() else float("nan")))
    return out


def baseline_labelling(match_fn, test: NeuronTable, templates: list[NeuronTable], use_colour: bool) -> Labelling:
    check_named(templates)
    per_template = [(match_fn(t, test, use_colour)[:, :-1], t.labels) for t in templates]
    names, probs = name_probabilities(per_template)
    return make_labelling(names, probs)


def pair_list(tables: list[NeuronTable], max_pairs: int | None, seed: int = 0) -> list[tuple[NeuronTable, NeuronTable]]:
    pairs = [(a, b) for i, a in enumerate(tables) for j, b in enumerate(tables) if i != j]
    if max_pairs is not None and len(pairs) > max_pairs:
        keep = np.random.default_rng(seed).choice(len(pairs), max_pairs, replace=False)
        pairs = [pairs[k] for k in sorted(keep)]
    return pairs


def mirrored_relative_to(atlas, worm: NeuronTable) -> bool:
    """Whether a labelled worm has the other handedness than the atlas (names give it: the best
    mirrored fit of its named neurons onto the atlas means is better than the best proper one);
    False with fewer than 4 names in common."""
    from .geometry import mirrored_by_names

    return bool(mirrored_by_names(atlas.names, atlas.mean, worm, min_names=4))


def handedness(worm: NeuronTable, reference: NeuronTable | None = None) -> str:
    """"same" or "mirrored": a labelled worm's handedness relative to a labelled ``reference``
    or, without one, to the built-in atlas — the value of ``--chirality`` for recordings made
    like it. Refuses a worm with fewer than 6 names in common (one line that says so)."""
    from .geometry import canonical_frame, mirrored_by_names, refuse_flat
    from .reference import load_atlas

    if reference is not None and not reference.named.any():
        raise FdlcError(f"{reference.source}: the reference has no named neuron (a 'label' column with names is needed)")
    if reference is None:
        atlas = load_atlas()
        names, xyz = atlas.names, atlas.mean
    else:
        names, xyz = reference.labels, canonical_frame(reference.xyz)[0]
    # A mirror image of a flat worm is the worm itself turned over: its handedness cannot be
    # told, nor a worm's relative to a flat reference. (Under 6 names: too few names, said below.)
    for table in (worm, reference) if reference is not None else (worm,):
        refuse_flat(table.xyz[table.named], table.source, min_neurons=6)
    # the answer comes from the names in common alone: flat there, a worm fits its mirror as well
    common = list(set(worm.labels[worm.named]) & {n for n in names if n})
    refuse_flat(worm.xyz[np.isin(worm.labels, common)], f"{worm.source} (its names in common with the reference)",
                min_neurons=6)
    if reference is not None:
        refuse_flat(reference.xyz[np.isin(reference.labels, common)],
                    f"{reference.source} (its names in common with the worm)", min_neurons=6)
    mirrored = mirrored_by_names(names, xyz, worm, min_names=6)
    if mirrored is None:
        raise FdlcError(f"{worm.source}: fewer than 6 named neurons in common with the reference; "
                        "the handedness needs at least 6 (label a few left/right pairs)")
    return "mirrored" if mirrored else "same"

