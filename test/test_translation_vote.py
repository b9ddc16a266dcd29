"""The pairing's translation vote counts exactly the cells its differences fall in."""
import numpy as np

from gls_calibration.registration.rigid import _rotation_2d, _TranslationVote


def _reference_votes(vote: _TranslationVote, measured_2d: np.ndarray) -> tuple[int, tuple[int, int]]:
    """The vote computed another way: cells of interleaved (N*K, 2) differences, counted with add.at."""
    differences = (vote.target_2d[:, None, :] - measured_2d[None, :, :]).reshape(-1, 2)
    cells = ((differences - vote.low) * (1.0 / vote.gate)).astype(np.int64)
    counts = np.zeros(vote.shape, dtype=np.int64)
    np.add.at(counts, (cells[:, 0], cells[:, 1]), 1)
    boxes = np.lib.stride_tricks.sliding_window_view(counts, (2, 2)).sum(axis=(2, 3))
    best_box = np.unravel_index(int(np.argmax(boxes)), boxes.shape)    # the first of equal boxes
    return int(boxes[best_box]), (int(best_box[0]), int(best_box[1]))


def test_votes_match_the_cells_of_every_difference():
    rng = np.random.default_rng(7)
    for _ in range(6):
        side = int(rng.integers(3, 12))
        axis = np.linspace(-95.0, 95.0, side)
        targets = np.stack(np.meshgrid(axis, axis), axis=-1).reshape(-1, 2)
        kept = rng.permutation(len(targets))[: max(3, int(0.8 * len(targets)))]
        measured = targets[kept] + rng.normal(0.0, 2.0, (1, 2)) + rng.normal(0.0, 0.05, (len(kept), 2))
        measured = np.vstack([measured, rng.uniform(-100.0, 100.0, (5, 2))])     # strays
        gate = float(rng.uniform(0.5, 5.0))
        vote = _TranslationVote(targets, float(np.max(np.linalg.norm(measured, axis=1))), gate)
        for angle in np.linspace(-0.26, 0.26, 5):
            rotated = measured @ _rotation_2d(angle).T
            assert vote.votes(rotated) == _reference_votes(vote, rotated)
