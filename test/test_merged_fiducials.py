"""The merged-pair test's statistics (``merged_fiducials.merged``) on signatures with known noise."""
import numpy as np
import pytest

from gls_calibration.fiducials.merged_pairs import SIGNATURE_DOF, merged

SECTORS = 24


def null_plate(count: int, seed: int):
    """Signatures of ``count`` single fiducials: a common part plus noise of a known covariance, and
    that covariance as a 24-sector jackknife would state it (its scatter included)."""
    rng = np.random.default_rng(seed)
    root = rng.normal(size=(SIGNATURE_DOF, SIGNATURE_DOF)) * 1e-3
    truth = root @ root.T + 1e-6 * np.eye(SIGNATURE_DOF)
    common = rng.normal(size=SIGNATURE_DOF) * 0.05
    signature = common + rng.multivariate_normal(np.zeros(SIGNATURE_DOF), truth, size=count)
    stated = np.array([np.cov(rng.multivariate_normal(np.zeros(SIGNATURE_DOF), truth, size=SECTORS), rowvar=False)
                       for _ in range(count)])
    return signature, stated, np.full(count, SECTORS), truth


def test_single_fiducials_are_not_called_merged():
    for seed in range(5):
        signature, covariance, groups, _ = null_plate(361, seed)
        assert not merged(signature, covariance, groups, np.ones(361, bool), 1e-7, 20).any()


def test_a_signature_far_beyond_its_noise_is_merged_and_nothing_else():
    signature, covariance, groups, truth = null_plate(100, 7)
    signature[17] += 40 * np.sqrt(np.diag(truth))
    flagged = merged(signature, covariance, groups, np.ones(100, bool), 1e-7, 20)
    assert np.nonzero(flagged)[0].tolist() == [17]


def test_what_every_fiducial_shares_is_not_a_pair():
    signature, covariance, groups, truth = null_plate(100, 8)
    shifted = signature + 100 * np.sqrt(np.diag(truth))
    assert not merged(shifted, covariance, groups, np.ones(100, bool), 1e-7, 20).any()


@pytest.mark.parametrize("references", [0, 19])
def test_too_few_references_call_nothing_merged(references):
    signature, covariance, groups, truth = null_plate(30, 9)
    signature[3] += 100 * np.sqrt(np.diag(truth))
    reference = np.arange(30) < references
    reference[3] = False
    assert not merged(signature, covariance, groups, reference, 1e-7, 20).any()


def test_unfitted_candidates_are_not_tested():
    signature, covariance, groups, _ = null_plate(40, 10)
    signature[5] = np.nan
    covariance[6] = np.nan
    groups[7] = SIGNATURE_DOF   # too few sectors for an F statistic
    signature[7] += 1.0
    flagged = merged(signature, covariance, groups, np.ones(40, bool), 1e-7, 20)
    assert not flagged[[5, 6, 7]].any()


def test_marks_that_truly_differ_widen_the_null_and_a_pair_still_stands_out():
    # A marking laser's power and focus wander: every single mark's signature differs from the
    # plate's by far more than its own noise. Those are not pairs; a signature far beyond that
    # spread still is one.
    signature, covariance, groups, truth = null_plate(361, 11)
    spread = 20 * np.sqrt(np.diag(truth))
    signature = signature + np.random.default_rng(12).normal(size=signature.shape) * spread
    reference = np.ones(361, bool)
    assert not merged(signature, covariance, groups, reference, 1e-5, 20).any()
    signature[40] += 12 * spread
    assert np.nonzero(merged(signature, covariance, groups, reference, 1e-5, 20))[0].tolist() == [40]
