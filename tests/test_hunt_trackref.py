"""Defect hunt (session 36), area "trackref": fdlc track with references other than the first
volume, several references, sequences of every shape, and the output's contract. Each test
fails on the code it was written against; its docstring says what is expected and what
happens instead."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest

from napari_fdlc.cli import main
from napari_fdlc.reference import generate_worm
from napari_fdlc.table import write_table
from napari_fdlc.track import SequenceParams, TrackSettings, join_by_time, simulate_sequence, track


@pytest.fixture(scope="module")
def worm2():
    return generate_worm(seed=2)


def test_chunk_does_not_change_the_answers_with_refine_steps_and_a_reference_file(worm2, shipped):
    """docs/tracking.md: `--chunk N` "does not change the answers with the default placement".
    With a reference that is not the first volume (a labelled file) and `--refine-steps 1`, chunk
    1 and chunk 16 give different track IDs to 24 neurons of 2 volumes: with chunk 1 the first
    volume's chunk ends with it, and `_match_chunk` then hands the next chunk the first volume's
    *refined* warp (`ref.warp = found[last]["warp"]`, as `rest` is empty), where within one
    chunk the geometric chain starts from the full search's warp (`chain = ref.warp`)."""
    volumes, _ = simulate_sequence(worm2, 2, SequenceParams(frames=3).scaled(3))
    answers = [track(volumes, [worm2], shipped, TrackSettings(chunk=chunk, refine_steps=1)) for chunk in (1, 16)]
    differ = [int((a != b).sum()) for a, b in zip(answers[0].track_id, answers[1].track_id)]
    assert differ == [0, 0, 0], differ
