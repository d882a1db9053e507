"""``fdlc``: the command line. Parse, call the core, print, exit codes — nothing else.

Every FdlcError becomes one line on stderr and exit status 2; nothing is written unless every
input was valid.
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

from .errors import FdlcError, check_output, one_line
from .geometry import CHIRALITIES

METHODS = ("fdlc", "cpd")


def _label_parser(sub) -> None:
    p = sub.add_parser("label", help="name the neurons of neuron tables", description="Name the neurons of one or more neuron tables.")
    # "*", not "+": `fdlc label --template T.csv TEST.csv` reads TEST.csv as a template, and
    # label_files then says so in words rather than argparse's "required: TEST.csv".
    p.add_argument("tests", nargs="*", metavar="TEST.csv", help="neuron tables to identify")
    p.add_argument("--template", action="extend", nargs="+", default=[], metavar="T.csv",
                   help="labelled neuron table(s) to take names from (--template a.csv b.csv, or repeated); "
                        "default: the built-in reference panel")
    p.add_argument("--no-color", "--no-colour", dest="no_colour", action="store_true", help="positions only")
    p.add_argument("--top-k", type=int, default=3, help="candidates written: the larger of K and 3 (default 3)")
    p.add_argument("--method", choices=METHODS, default="fdlc", help="fdlc (default) or cpd (classical baseline; needs --template)")
    p.add_argument("--weights", help="model weights (path without suffix); default: the shipped model")
    p.add_argument("--chirality", choices=CHIRALITIES, default="auto",
                   help="handedness of the tests relative to the template(s) or the built-in atlas: auto (default) "
                        "tries both; same / mirrored when you know your microscope (see docs/cli.md)")
    p.add_argument("--shared-handedness", action=argparse.BooleanOptionalAction, default=None,
                   help="with several tests, --chirality auto and no template (the default there): the tests come from "
                        "one microscope, so name them all in one handedness when they clearly lean one way (a sign "
                        "test; see docs/cli.md); --no-shared-handedness decides for each test alone")
    p.add_argument("--adapt-colours", "--adapt-colors", dest="adapt_colours", action=argparse.BooleanOptionalAction,
                   default=None,
                   help="with no template, colour and at least 3 tests (the default there): measure the panel's colour "
                        "per name on the tests' confident names, then name them again (see docs/cli.md); "
                        "--no-adapt-colours names each test with the panel as it ships")
    p.add_argument("--no-atlas", dest="use_atlas", action="store_false",
                   help="with --template: names from the template(s) alone, without the built-in atlas's own answer")
    p.add_argument("--out", required=True, help="output CSV (one test) or directory (several tests)")
    p.set_defaults(run=_run_label)


def _run_label(args) -> int:
    from .label import label_files

    label_files(
        tests=args.tests,
        templates=args.template,
        out=args.out,
        use_colour=not args.no_colour,
        top_k=args.top_k,
        method=args.method,
        weights=args.weights,
        chirality=args.chirality,
        shared_handedness=args.shared_handedness,
        use_atlas=args.use_atlas,
        adapt_colours=args.adapt_colours,
    )
    return 0


def _simulate_parser(sub) -> None:
    p = sub.add_parser("simulate", help="make synthetic worms with known correspondence from a neuron table")
    p.add_argument("table", help="source neuron table")
    p.add_argument("--count", type=int, default=1, help="synthetic worms to make (default 1)")
    p.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    p.add_argument("--out", required=True, help="output folder: <stem>_synN.csv with an 'origin' column")
    p.set_defaults(run=_run_simulate)


def _run_simulate(args) -> int:
    import numpy as np

    from .simulate import simulate_worm
    from .table import read_volume, warn_implausible_scales, write_table

    if args.count < 1:
        raise FdlcError("--count must be at least 1")
    if args.seed < 0:
        raise FdlcError(f"--seed must be 0 or more (got {args.seed})")
    out = Path(args.out)
    if not args.out:
        raise FdlcError("--out: give the folder that receives the synthetic worms")
    if out.exists() and not out.is_dir():
        raise FdlcError(f"{out}: --out must be a folder (it receives <stem>_synN.csv), not a file")
    table = read_volume(args.table, "give one time point (one worm) to simulate from")
    # Every output checked before the first is written: nothing is written unless all can be
    # (and before any warning: a refusal is one line).
    paths = [check_output(out / f"{Path(args.table).stem}_syn{k}.csv", [args.table], create_folder=True)
             for k in range(args.count)]
    warn_implausible_scales([table])  # the recipe's magnitudes are in µm
    rng = np.random.default_rng(args.seed)
    for path in paths:
        synth = simulate_worm(table, rng)
        df = synth.table.to_dataframe()
        df["origin"] = synth.origin
        write_table(df, path)
        print(path)
    return 0


def _train_parser(sub) -> None:
    p = sub.add_parser("train", help="train the correspondence model on the annotated corpus")
    p.add_argument("--config", help="JSON training configuration (a checkpoint's .json works: its train_config is used); flags override it")
    p.add_argument("--corpus", help="folder with worms.csv (default: ../shared/data/neuropal_corpus or $FDLC_CORPUS)")
    p.add_argument("--train-labs", nargs="+", default=None)
    p.add_argument("--val-labs", nargs="+", default=None)
    p.add_argument("--steps", type=int, default=None)
    p.add_argument("--batch-size", type=int, default=None)
    p.add_argument("--minutes", type=float, default=None, help="stop after this many minutes")
    p.add_argument("--stop-at", type=int, default=None, help="stop after this step (the LR schedule still spans --steps)")
    p.add_argument("--seed", type=int, default=None, help="random seed (default 0)")
    p.add_argument("--threads", type=int, default=None)
    p.add_argument("--workers", type=int, default=None,
                   help="processes that make training examples (worth it beside a GPU; default 0)")
    p.add_argument("--device", default=None, help="torch device (default: cuda when present, else cpu)")
    p.add_argument("--resume", action="store_true", help="continue from the checkpoint at --out")
    p.add_argument("--init-from", help="start from these weights (path without suffix; keys that fit)")
    p.add_argument("--colour-input", action="store_true", help="give the model NeuroPAL colour as an input")
    p.add_argument("--eval-every", type=int, default=None, help="validate every N steps")
    p.add_argument("--val-pairs-per-lab", type=int, default=None)
    p.add_argument("--no-calibrate", action="store_true", help="skip fitting colour weight and temperature")
    p.add_argument("--calibrate-only", action="store_true", help="only calibrate the checkpoint at --out")
    p.add_argument("--out", default=None, help="checkpoint path without suffix (default runs/model)")
    p.set_defaults(run=_run_train)


def _run_train(args) -> int:
    from .errors import model_files
    from .train import TrainConfig, train

    if args.resume and args.init_from:
        raise FdlcError("--resume continues the checkpoint at --out and --init-from starts a new run from other weights: give one")
    if args.no_calibrate and args.calibrate_only:
        raise FdlcError("--no-calibrate and --calibrate-only ask for opposite things: give one")
    if args.config:
        cfg = TrainConfig.from_json(args.config)
    elif args.resume or args.calibrate_only:
        # The checkpoint's own run (labs, split, schedule): the defaults would calibrate a
        # leave-one-lab-out fold on the very lab it holds out.
        cfg = TrainConfig.from_checkpoint(model_files(args.out or TrainConfig.out)[1])
    else:
        cfg = TrainConfig()
    given = {"corpus": args.corpus, "threads": args.threads, "time_limit_min": args.minutes,
             "init_from": args.init_from, "stop_at": args.stop_at, "workers": args.workers,
             "device": args.device}
    for key, value in given.items():
        if value is not None:
            setattr(cfg, key, value)
    cfg.seed = args.seed if args.seed is not None else cfg.seed
    if args.config and not (args.out or args.resume or args.calibrate_only) and \
            model_files(cfg.out)[1].resolve() == Path(args.config).resolve():
        raise FdlcError(f"{args.config}: a new run from this checkpoint's configuration would replace the checkpoint; "
                        "give --out (or --resume to continue it)")
    cfg.out = args.out or cfg.out
    cfg.resume = args.resume or cfg.resume  # a recipe's "resume": true (a checkpoint's record clears it)
    if args.no_calibrate:  # else the configuration's own choice
        cfg.calibrate = False
    if args.colour_input:
        cfg.model = {**cfg.model, "colour_channels": 3}
    if args.eval_every is not None:
        cfg.eval_every = args.eval_every
    if args.val_pairs_per_lab is not None:
        cfg.val_pairs_per_lab = args.val_pairs_per_lab
    if args.train_labs is not None:
        cfg.train_labs = tuple(args.train_labs)
    if args.val_labs is not None:
        cfg.val_labs = tuple(args.val_labs)
    if args.steps is not None:
        cfg.steps = args.steps
    if args.batch_size is not None:
        cfg.batch_size = args.batch_size
    cfg.check()
    if str(cfg.out).endswith(("/", os.sep)) or not Path(cfg.out).name:
        raise FdlcError(f"--out {cfg.out}: give the checkpoint's path without suffix, such as runs/model")
    # Refused before training, not at the first save: a folder that cannot be made, or the very
    # weights a new run starts from.
    starts_from = [model_files(cfg.init_from)[0]] if cfg.init_from and not cfg.resume else []
    from .corpus import refuse_out_in_corpus

    refuse_out_in_corpus(model_files(cfg.out)[0], cfg.corpus, "checkpoint")  # before its folder is made
    check_output(model_files(cfg.out)[0], inputs=starts_from, create_folder=True)
    if not args.calibrate_only:  # the record too (a folder of its name failed at the first save); a new
        # run's record would replace its recipe
        check_output(model_files(cfg.out)[1], inputs=[args.config] if args.config and not cfg.resume else [],
                     create_folder=True)
    if args.calibrate_only and cfg.task != "identify":
        raise FdlcError("--calibrate-only: a tracking model has no inference settings to fit (they stay at their defaults)")
    if args.calibrate_only:
        from .train import calibrate_checkpoint

        calibrate_checkpoint(cfg)
        return 0
    result = train(cfg)
    weights, _ = model_files(cfg.out)
    if result["best_mean_top1"] < 0:
        raise FdlcError(f"no checkpoint was saved at {weights}")
    print(f"best mean validation top-1 {result['best_mean_top1']:.3f} after {result['minutes']:.1f} min; weights at {weights}")
    return 0


def _handedness_parser(sub) -> None:
    p = sub.add_parser("handedness", help="which --chirality fits recordings like these labelled worms",
                       description="Print the handedness of labelled neuron tables relative to the built-in atlas "
                                   "(or a template): the --chirality to use for recordings made the same way.")
    p.add_argument("tables", nargs="+", metavar="LABELLED.csv", help="neuron tables with a label column")
    p.add_argument("--template", metavar="T.csv", help="relative to this labelled table instead of the built-in atlas")
    p.set_defaults(run=_run_handedness)


def _run_handedness(args) -> int:
    from .evaluate import handedness
    from .table import read_volume

    one = "give one time point (one labelled worm) per table"
    tables = [read_volume(t, one) for t in args.tables]  # all read (and refused) before any answer
    reference = read_volume(args.template, one) if args.template else None
    answers = [handedness(t, reference) for t in tables]
    for path, answer in zip(args.tables, answers):
        print(f"{path}: {answer}")
    same, mirrored = answers.count("same"), answers.count("mirrored")
    if same != mirrored:  # one worm too: the advice is what the command is for
        majority = "same" if same > mirrored else "mirrored"
        print(f"{max(same, mirrored)} of {len(answers)} {majority}: use --chirality {majority}")
    elif len(answers) > 1:
        print(f"{same} same, {mirrored} mirrored: no majority; check how these recordings were made")
    return 0


def _atlas_parser(sub) -> None:
    p = sub.add_parser("atlas", help="build the reference atlas (the built-in panel) from an annotated corpus")
    p.add_argument("--corpus", help="folder with worms.csv (default: ../shared/data/neuropal_corpus or $FDLC_CORPUS)")
    p.add_argument("--labs", nargs="+", default=None, help="labs to use (default: all)")
    p.add_argument("--min-frequency", type=float, default=0.2,
                   help="keep names seen in at least this fraction of worms (default 0.2), and in two at least")
    p.add_argument("--out", required=True, help="atlas CSV (the shipped one is src/napari_fdlc/data/atlas.csv)")
    p.set_defaults(run=_run_atlas)


def _run_atlas(args) -> int:
    from .corpus import load_corpus, refuse_out_in_corpus
    from .reference import build_atlas

    if not 0 < args.min_frequency <= 1:
        raise FdlcError(f"--min-frequency must be a fraction of worms in (0, 1] (got {args.min_frequency})")
    refuse_out_in_corpus(Path(args.out), args.corpus, "atlas")  # before its folder is made
    check_output(args.out, create_folder=True)
    atlas = build_atlas(load_corpus(args.corpus, args.labs), min_frequency=args.min_frequency)
    atlas.save(args.out)
    print(f"{len(atlas.names)} names from {atlas.worms} worms of {', '.join(atlas.labs)} -> {args.out}")
    return 0


class _Parser(argparse.ArgumentParser):
    """Usage mistakes are bad input too: one line on stderr (``--help`` has the usage), exit 2."""

    def error(self, message):
        self.exit(2, f"{self.prog}: {message} (see {self.prog} --help)\n")

    def parse_known_args(self, args=None, namespace=None):
        """An empty value (an unset shell variable: ``--out "$OUT"``) is refused: taken as not
        given, ``--out ""`` trained into the default checkpoint and ``--weights ""`` used the
        shipped model without a word."""
        namespace, extras = super().parse_known_args(args, namespace)
        for action in self._actions:
            value = getattr(namespace, action.dest, None)
            if any(isinstance(v, str) and not v.strip() for v in (value if isinstance(value, list) else [value])):
                if action.option_strings:
                    self.error(f"{action.option_strings[0]} was given an empty value: give one or leave the option out")
                self.error(f"an empty {action.metavar or action.dest} was given")
        return namespace, extras


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(prog="fdlc", description="Identify and track C. elegans neurons (fDLC).")
    sub = parser.add_subparsers(dest="command", required=True, parser_class=_Parser)
    _label_parser(sub)
    try:
        from . import _cli_segment
    except ImportError:  # the image side is optional for the core
        _cli_segment = None
    if _cli_segment is not None:
        p = sub.add_parser("segment", help="detect nuclei in a 3D stack and write a neuron table")
        _cli_segment.add_arguments(p)
        p.set_defaults(run=_cli_segment.run)
    _simulate_parser(sub)
    _train_parser(sub)
    _atlas_parser(sub)
    _handedness_parser(sub)
    for name, module in (("evaluate", "_cli_evaluate"), ("track", "_cli_track")):
        try:
            mod = __import__(f"napari_fdlc.{module}", fromlist=["add_arguments", "run"])
        except ImportError:
            continue
        p = sub.add_parser(name, help=mod.__doc__.strip().splitlines()[0] if mod.__doc__ else None)
        mod.add_arguments(p)
        p.set_defaults(run=mod.run)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        return int(args.run(args) or 0)
    except FdlcError as exc:
        print(f"fdlc: error: {one_line(exc)}", file=sys.stderr)
        return 2
    except OSError as exc:  # a file the system would not read or write (inputs are checked before)
        where = f"{exc.filename}: " if exc.filename else ""
        print(f"fdlc: error: {one_line(f'{where}{exc.strerror or exc}')}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("fdlc: interrupted", file=sys.stderr)
        return 130
    except MemoryError:
        print("fdlc: error: out of memory", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
