"""The skin-artefact generator: amplitudes as asked, deformation free of rigid motion, truth untouched."""

from __future__ import annotations

import numpy as np
import pytest

from jointfit_core.soft_tissue import STA_MODES, _features, _skew_rows, skin_artefact, skin_markers_at
from jointfit_core.synthetic import two_segment_motion


@pytest.mark.parametrize("mode", STA_MODES)
def test_amplitude_is_the_rms_displacement(mode: str) -> None:
    rng = np.random.default_rng(3)
    motion = two_segment_motion(rng, kind="ball")
    t = np.arange(1200) / 60.0
    p0, c0 = motion.markers_at(t)
    p, c = skin_markers_at(np.random.default_rng(4), motion, t, parent_mm=5.0, child_mm=12.0, mode=mode)
    for clean, skin, amp in ((p0, p, 5.0), (c0, c, 12.0)):
        rms = np.sqrt(((skin - clean) ** 2).sum(axis=2).mean())
        assert rms == pytest.approx(amp, rel=1e-9)


def test_deformation_has_no_rigid_part_and_rigid_share_splits_the_amplitude() -> None:
    rng = np.random.default_rng(5)
    motion = two_segment_motion(rng, kind="hinge")
    t = np.arange(900) / 60.0
    feats = _features(np.outer(np.sin(t), [1.0, 0.3, -0.2]))
    field = skin_artefact(rng, motion.template_child, feats, amplitude=10.0, rigid_share=0.75)
    x = motion.template_child - motion.template_child.mean(axis=0)
    G = _skew_rows(x)
    # every deformation field is orthogonal to every small rigid motion of the cluster
    assert np.abs(field.deformation.reshape(9, -1) @ G).max() < 1e-9 * np.abs(G).max()
    # and every rigid field is one
    rigid = field.rigid.reshape(9, -1)
    fit = rigid @ np.linalg.pinv(G).T @ G.T
    assert np.allclose(fit, rigid, atol=1e-9)

    def rms(f: np.ndarray) -> float:
        return float(np.sqrt((np.einsum("nf,fpi->npi", feats, f) ** 2).sum(axis=2).mean()))

    assert rms(field.rigid) == pytest.approx(7.5, rel=1e-9)
    assert rms(field.deformation) == pytest.approx(10.0 * np.sqrt(1 - 0.75**2), rel=1e-9)


def test_no_artefact_is_the_rigid_motion_plus_noise() -> None:
    rng = np.random.default_rng(6)
    motion = two_segment_motion(rng, kind="ball")
    t = np.arange(300) / 100.0
    p0, c0 = motion.markers_at(t)
    p, c = skin_markers_at(rng, motion, t)
    assert np.array_equal(p, p0) and np.array_equal(c, c0)
    p, _ = skin_markers_at(rng, motion, t, noise_std=0.5)
    assert np.std(p - p0) == pytest.approx(0.5, rel=0.05)
