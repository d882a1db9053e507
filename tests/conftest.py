"""Shared fixtures: small worms generated from the shipped atlas (no corpus needed) and a
real, untrained model saved as safetensors (fast, and independent of the shipped weights)."""

from __future__ import annotations

import numpy as np
import pytest

from napari_fdlc.corpus import default_corpus_path
from napari_fdlc.reference import generate_worm
from napari_fdlc.table import NeuronTable, write_table


@pytest.fixture(scope="session")
def worm() -> NeuronTable:
    return generate_worm(seed=1)


@pytest.fixture(scope="session")
def other_worm() -> NeuronTable:
    return generate_worm(seed=2)


@pytest.fixture
def gap_table() -> NeuronTable:
    """20 named neurons with R, G, B, W; neuron 3 has no R reading."""
    rng = np.random.default_rng(0)
    colours = {c: rng.uniform(1, 2, 20) for c in ("R", "G", "B", "W")}
    colours["R"][3] = np.nan
    return NeuronTable(rng.uniform(0, 40, (20, 3)), colours, labels=np.array([f"N{k}" for k in range(20)], dtype=object))


@pytest.fixture(scope="session")
def untrained_weights(tmp_path_factory):
    import torch

    from napari_fdlc.model import CorrespondenceModel, save_model

    torch.manual_seed(0)
    path = tmp_path_factory.mktemp("weights") / "model"
    save_model(CorrespondenceModel({"layers": 1, "dim": 32}), path, {"inference": {"refine_steps": 1}})
    return path


@pytest.fixture(scope="module")
def shipped():
    """The shipped model: where the behaviour tested depends on a trained model's answers."""
    from napari_fdlc.identify import Identifier

    return Identifier.load(device="cpu")


@pytest.fixture
def table_files(tmp_path, worm, other_worm):
    test = tmp_path / "test.csv"
    template = tmp_path / "template.csv"
    write_table(worm, test)
    write_table(other_worm, template)
    return test, template


@pytest.fixture(scope="session")
def corpus_path():
    path = default_corpus_path()
    if path is None:
        pytest.skip("NeuroPAL corpus not available (set FDLC_CORPUS)")
    return path


def _write_corpus(root, tables: dict[str, list[NeuronTable]]):
    """``tables`` ({lab: [worm tables]}) written under ``root`` as a corpus (one CSV per worm
    and worms.csv), to read as corpus.load_corpus reads ../shared's."""
    root.mkdir(parents=True, exist_ok=True)
    rows = ["dataset,dandiset,worm,n_neurons,n_labeled"]
    for lab, worms in tables.items():
        (root / lab).mkdir(exist_ok=True)
        for i, table in enumerate(worms):
            write_table(table, root / lab / f"w{i}.csv")
            rows.append(f"{lab},0,w{i},{len(table)},{int(table.named.sum())}")
    (root / "worms.csv").write_text("\n".join(rows) + "\n")
    return root


@pytest.fixture(scope="session")
def write_corpus():
    """:func:`_write_corpus`, for tests that train or evaluate on a small corpus of their own."""
    return _write_corpus


def random_table(n: int, seed: int = 0, named: bool = True) -> NeuronTable:
    rng = np.random.default_rng(seed)
    xyz = rng.normal(0, 1, (n, 3)) * [40, 8, 6] + [60, 30, 15]
    labels = np.array([f"N{i}" if named else "" for i in range(n)], dtype=object)
    colours = {c: rng.gamma(2.0, 100.0, n) for c in "RGB"}
    return NeuronTable(xyz, colours, labels)


@pytest.fixture(autouse=True, scope="session")
def _one_torch_thread():
    """Small tensors run fastest on one thread; and the suite must not fight a second job."""
    try:
        import torch
    except ImportError:
        return
    torch.set_num_threads(1)


@pytest.fixture(scope="session")
def recording(tmp_path_factory):
    """A short rendered recording of one moving worm, as an OME-TIFF with a time axis: (path,
    the rendered truth per time point, the source neuron of each true neuron per time point)."""
    from napari_fdlc.io.images import write_tiff
    from napari_fdlc.render import random_worm, render_recording
    from napari_fdlc.track import SequenceParams, simulate_sequence

    worm = random_worm(45, size_um=(44, 16, 12), min_spacing_um=2.6, seed=5)
    gentle = SequenceParams(frames=3, bend_curvature=0.002, roll=0.05, xy_rotation=0.2, drift_um=2.0,
                            drop_fraction=(0.0, 0.0), max_spurious=0, jitter_um=0.1)
    volumes, origins = simulate_sequence(worm, 1, gentle)
    series, truths = render_recording(volumes, origins, voxel_size_zyx=(1.5, 0.35, 0.35), gut=False, seed=2)
    path = tmp_path_factory.mktemp("recording") / "recording.ome.tif"
    write_tiff(path, series)
    return path, truths, origins


@pytest.fixture
def small_tables(tmp_path):
    """template.csv, test.csv (generated worms) and recording.csv (3 time points, a t column)."""
    import pandas as pd

    write_table(generate_worm(seed=0), tmp_path / "template.csv")
    write_table(generate_worm(seed=1), tmp_path / "test.csv")
    worm = pd.read_csv(tmp_path / "template.csv")
    rng = np.random.default_rng(0)
    frames = []
    for t in range(3):
        f = worm.copy()
        f[["x_um", "y_um", "z_um"]] += rng.normal(0, 0.3, (len(f), 3))
        f["t"] = t
        f["label"] = ""
        frames.append(f)
    write_table(pd.concat(frames, ignore_index=True), tmp_path / "recording.csv")
    return tmp_path
