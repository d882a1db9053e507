"""Self-training on a new lab's own recordings (an experiment; nothing of it ships).

    python benchmarks/self_training.py --lab EY [--minutes 8]

For the leave-one-lab-out fold of ``--lab`` (``runs/fold_<LAB>/model``, trained without the lab):

1. the fold model names every worm of the lab with the panel (built without the lab), the
   worms in one call with the handedness shared and the colours adapted (``fdlc label
   --shared-handedness --adapt-colours``); names given with confidence >= 0.5 are kept as
   pseudo-labels, the true names are never read for training;
2. a temporary corpus holds those pseudo-labelled worms beside the other four labs' real ones
   (links to the corpus folders, in a temporary directory: nothing is copied into the project);
3. ``fdlc train`` continues the fold model on it (the fold's recipe, learning rate 2.5e-4,
   ``--minutes``, seed 1, one thread, then its usual calibration), and a control run continues it
   the same way on the four labs alone, so that the gain of training longer is told apart from
   the gain of the pseudo-labels;
4. the three models are scored on the lab's true names: the panel on the lab's worms in one
   call (handedness shared, then colours adapted) and pairs within the lab with colour.

Prints a markdown table. Needs the fold models (benchmarks/leave_one_lab_out.py --train).
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "src"))

import numpy as np  # noqa: E402

from napari_fdlc.cli import main as fdlc  # noqa: E402
from napari_fdlc.corpus import default_corpus_path, load_corpus  # noqa: E402
from napari_fdlc.evaluate import Scores, pair_list  # noqa: E402
from napari_fdlc.identify import Identifier  # noqa: E402
from napari_fdlc.reference import build_atlas, make_panel  # noqa: E402
from napari_fdlc.table import NeuronTable, write_table  # noqa: E402

PSEUDO_MIN_CONF = 0.5


def pseudo_corpus(corpus: Path, lab: str, worms, results, out: Path) -> tuple[int, float]:
    """The corpus folder layout at ``out``: the other labs linked, ``lab`` pseudo-labelled.
    Returns the number of pseudo-names kept and the fraction of them that are right."""
    index = (corpus / "worms.csv").read_text()
    (out / "worms.csv").write_text(index)
    for other in {line.split(",")[0] for line in index.splitlines()[1:]} - {lab}:
        (out / other).symlink_to(corpus / other)
    (out / lab).mkdir()
    kept = right = 0
    for worm, result in zip(worms, results):
        ids = np.asarray(result.auto_id, dtype=object)
        labels = np.where(np.asarray(result.auto_conf) >= PSEUDO_MIN_CONF, ids, "")
        write_table(NeuronTable(worm.table.xyz, worm.table.colours, labels), out / lab / f"{worm.name}.csv")
        named = labels != ""
        kept, right = kept + int(named.sum()), right + int((labels[named] == worm.table.labels[named]).sum())
    return kept, right / max(kept, 1)


def score(weights: str, lab: str, corpus) -> dict:
    """Top-1 and ECE on the lab's true names (see the module docstring, step 4)."""
    identifier = Identifier.load(weights)
    tests = [w.table for w in corpus if w.lab == lab]
    atlas = build_atlas([w for w in corpus if w.lab != lab])
    panel = make_panel(atlas)
    out = {}
    for key, adapt in (("panel, one call", False), ("panel, one call, colours adapted", True)):
        scores = Scores()
        for test, result in zip(tests, identifier.label_panel_many(tests, panel, adapt_colours=adapt)):
            scores.add(result, test, panel.names)
        out[key] = scores.summary()
    scores = Scores()
    for template, test in pair_list(tests, 20, seed=0):
        scores.add(identifier.label(test, [template], use_colour=True, atlas=atlas), test, set(template.names))
    out["pairs with colour"] = scores.summary()
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--lab", required=True)
    ap.add_argument("--minutes", type=float, default=8.0)
    ap.add_argument("--corpus", default=None)
    ap.add_argument("--out", default="runs/self_training", help="where the two continued models go")
    args = ap.parse_args(argv)
    corpus_path = Path(args.corpus) if args.corpus else default_corpus_path()
    corpus = load_corpus(corpus_path)
    fold = f"runs/fold_{args.lab}/model"
    worms = [w for w in corpus if w.lab == args.lab]
    panel = make_panel(build_atlas([w for w in corpus if w.lab != args.lab]))
    first = Identifier.load(fold).label_panel_many([w.table for w in worms], panel, adapt_colours=True)
    recipe = json.loads(Path(fold).with_suffix(".json").read_text())["train_config"]
    models = {"fold model": fold}
    with tempfile.TemporaryDirectory() as tmp:
        kept, right = pseudo_corpus(corpus_path, args.lab, worms, first, Path(tmp))
        print(f"{args.lab}: {kept} pseudo-names kept, {100 * right:.1f} % right", file=sys.stderr, flush=True)
        for name, labs in (("continued, four labs (control)", recipe["train_labs"]),
                           ("continued, four labs + the lab's pseudo-names", recipe["train_labs"] + [args.lab])):
            out = f"{args.out}/{args.lab}_{'pseudo' if args.lab in labs else 'control'}/model"
            config = dict(recipe, corpus=tmp, train_labs=labs, init_from=fold, lr=2.5e-4, steps=1500,
                          eval_every=250, time_limit_min=args.minutes, seed=1, out=out)
            config_path = Path(tmp) / "config.json"
            config_path.write_text(json.dumps(config))
            if fdlc(["train", "--config", str(config_path), "--threads", "1"]) != 0:
                return 1
            models[name] = out
    rows = {name: score(path, args.lab, corpus) for name, path in models.items()}
    columns = ["panel, one call", "panel, one call, colours adapted", "pairs with colour"]
    print(f"\n{args.lab}: {kept} pseudo-names (confidence >= {PSEUDO_MIN_CONF}), {100 * right:.1f} % of them right; "
          f"{args.minutes:g} minutes of training each.\n")
    print("| model | " + " | ".join(f"{c}: top-1 (ECE)" for c in columns) + " |")
    print("|---|" + "---|" * len(columns))
    for name, result in rows.items():
        print(f"| {name} | " + " | ".join(f"{100 * result[c]['top1']:.1f} ({result[c]['ece']:.3f})" for c in columns) + " |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
