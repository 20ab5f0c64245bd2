"""The comparison logic of benchmarks/pixels.py (pure numpy; the benchmark itself needs the reference venv)."""

from __future__ import annotations

import numpy as np

from impulse.benchmarks.pixels import compare_images, differing, not_uniform


def _image() -> np.ndarray:
    image = np.ones((20, 20, 3), np.float32)
    image[5:10, 5:10] = (0.0, 0.8, 0.0)  # a green square
    return image


def test_identical_images_have_no_differences() -> None:
    image = _image()
    result = compare_images(image, image.copy(), np.zeros((0, 2), int), np.zeros((0, 2), int), 4)
    assert result["differing"] == 0 and result["fraction"] == 0.0 and sum(result["classes"].values()) == 0


def test_boundary_interior_joint_and_thruster_classes() -> None:
    reference = _image()
    ours = reference.copy()
    ours[5, 7] = 1.0  # a flipped boundary pixel of the square
    ours[15, 15] = 0.0  # a wrong pixel in the uniform background, far from everything
    ours[2, 17] = 0.0  # next to a joint at (2, 16)
    ours[17, 3] = 0.0  # inside the window of a thruster at (16, 2)
    result = compare_images(ours, reference, np.asarray([[2, 16]]), np.asarray([[16, 2]]), 4)
    assert result["differing"] == 4
    assert result["classes"] == {"thruster": 1, "joint": 1, "edge": 1, "interior": 1}
    assert result["max_abs"] == 1.0
    assert differing(ours, reference).sum() == 4
    edges = not_uniform(reference)
    assert edges[5, 7] and edges[4, 7] and not edges[7, 7] and not edges[15, 15]
