"""The colour check of an edge (`gscan.registration.colour`, `dense.colour_agreement`): a textured plane seen
by one camera, posed right, posed turned 180 deg about the optical axis (every depth sample lands back on the
plane, so the depth cannot refute it), and without texture."""
from __future__ import annotations

import cv2
import numpy as np
import pytest

from gscan.geometry.transforms import make_T
from gscan.io.camera import Intrinsics
from gscan.registration.colour import image_noise
from gscan.registration.dense import DenseGeometry, colour_agreement, depth_agreement
from gscan.registration.noise import DepthNoise

W, H = 320, 240
INTR = Intrinsics(300.0, 300.0, (W - 1) / 2, (H - 1) / 2, W, H)  # principal point at the image's centre
NOISE = DepthNoise()


def _texture(seed: int) -> np.ndarray:
    """[H x W x 3] uint8: blurred noise, texture at a few pixels' scale, like print or wood grain."""
    rng = np.random.default_rng(seed)
    g = cv2.GaussianBlur(rng.uniform(0, 255, (H, W)).astype(np.float32), (0, 0), 1.5)
    g = (g - g.mean()) / g.std() * 40 + 128
    return np.repeat(np.clip(g, 0, 255).astype(np.uint8)[..., None], 3, axis=2)


def _plane(image: np.ndarray) -> DenseGeometry:
    return DenseGeometry.from_depth(np.full((H, W), 1.0, np.float32), INTR, image=image)


def test_right_pose_lines_up_and_a_turned_one_does_not_though_the_depth_agrees():
    g = _plane(_texture(0))
    right = colour_agreement(g, g, np.eye(4), NOISE)
    assert right.informative >= 40 and right.agreeing_fraction > 0.9, right
    turned = make_T(np.diag([-1.0, -1.0, 1.0]), np.zeros(3))  # 180 deg about the optical axis
    assert depth_agreement(g, g, turned, NOISE).see_through == 0  # the depth cannot tell
    wrong = colour_agreement(g, g, turned, NOISE)
    # unrelated texture passes a tile's rank test against 16 baselines about 1 time in 17
    assert wrong.informative >= 40 and wrong.agreeing_fraction < 1 / 3, wrong


def test_another_texture_does_not_line_up():
    a, b = _plane(_texture(0)), _plane(_texture(1))
    c = colour_agreement(a, b, np.eye(4), NOISE)
    assert c.informative >= 40 and c.agreeing_fraction < 1 / 3, c


def test_no_texture_gives_no_verdict():
    rng = np.random.default_rng(2)
    flat = np.clip(128 + rng.normal(0, 2.0, (H, W, 1)), 0, 255).astype(np.uint8).repeat(3, axis=2)
    g = _plane(flat)
    assert colour_agreement(g, g, np.eye(4), NOISE).informative == 0  # pixel noise alone is no texture
    assert colour_agreement(_plane(_texture(0)), DenseGeometry.from_depth(np.full((H, W), 1.0), INTR),
                            np.eye(4), NOISE).informative == 0  # a frame without its image


@pytest.mark.parametrize("sigma", [1.0, 3.0, 8.0])
def test_image_noise_is_estimated_from_the_image(sigma):
    """Immerkaer's estimator on a smooth ramp plus Gaussian noise: within 5 % (the estimate's relative standard
    error over 76 000 pixels is about 0.3 %; the ramp adds nothing, its second differences are zero)."""
    rng = np.random.default_rng(3)
    ramp = np.add.outer(np.linspace(0, 60, H), np.linspace(0, 90, W))
    assert image_noise(ramp + rng.normal(0, sigma, (H, W))) == pytest.approx(sigma, rel=0.05)
