"""Frames brought to the network size: the authors' Pillow filter and point sampling."""
import numpy as np
import pytest
from PIL import Image

from parq_runtime import preprocess
from parq_runtime.errors import ParqError

K_LARGE = np.array([[300.0, 0, 159.5], [0, 300.0, 119.5], [0, 0, 1]])


def test_frames_at_the_network_size_pass_unchanged_under_either_filter():
    image = np.random.default_rng(0).integers(0, 256, (120, 160, 3), dtype=np.uint8)
    K = K_LARGE / [[2], [2], [1]]
    for name in preprocess.FILTERS:
        out, K_out = preprocess.prepare(image, K, (160, 120), name)
        np.testing.assert_array_equal(out, image)
        np.testing.assert_array_equal(K_out, K)


def test_pillow_filter_is_pillows_bilinear_resize_with_the_authors_intrinsics():
    image = np.random.default_rng(1).integers(0, 256, (240, 320, 3), dtype=np.uint8)
    out, K = preprocess.prepare(image, K_LARGE, (160, 120))
    np.testing.assert_array_equal(
        out, np.asarray(Image.fromarray(image).resize((160, 120), Image.BILINEAR)))
    np.testing.assert_allclose(K, K_LARGE / [[2], [2], [1]])


def test_point_samples_are_the_pixels_whose_rays_the_scaled_intrinsics_name():
    """A marker on the pixel a world point projects to in the large frame lands, after point
    sampling, on the pixel the scaled intrinsics project it to: the geometry is exact for a
    whole-number ratio, and off by at most half a large pixel for any other."""
    rng = np.random.default_rng(2)
    for size in ((160, 120), (100, 75), (64, 48)):
        for _ in range(20):
            u, v = rng.integers(0, size[0]), rng.integers(0, size[1])
            x = preprocess.point_samples(320, size[0])[u]
            y = preprocess.point_samples(240, size[1])[v]
            point_camera = np.linalg.solve(K_LARGE, [x, y, 1.0]) * rng.uniform(0.5, 5)
            image = np.zeros((240, 320, 3), np.uint8)
            image[y, x] = 255
            out, K = preprocess.prepare(image, K_LARGE, size, "point")
            assert out.shape == (size[1], size[0], 3)
            (row,), (col,) = np.nonzero(out[..., 0])
            projected = (K @ point_camera)[:2] / point_camera[2]
            assert (col, row) == (u, v)
            half = 0.5 * np.array([size[0] / 320, size[1] / 240])
            assert np.all(np.abs(projected - [u, v]) <= half + 1e-9)
            if size == (160, 120):
                np.testing.assert_allclose(projected, [u, v], atol=1e-9)


def test_point_sampling_a_whole_ratio_takes_every_kth_pixel():
    image = np.random.default_rng(3).integers(0, 256, (240, 320, 3), dtype=np.uint8)
    out, K = preprocess.prepare(image, K_LARGE, (80, 60), "point")
    np.testing.assert_array_equal(out, image[::4, ::4])
    np.testing.assert_allclose(K, K_LARGE / [[4], [4], [1]])
    np.testing.assert_array_equal(preprocess.point_samples(10, 4), [0, 2, 5, 8])
    np.testing.assert_array_equal(preprocess.point_samples(3, 7), [0, 0, 1, 1, 2, 2, 2])


def test_unknown_filter_is_refused():
    image = np.zeros((240, 320, 3), np.uint8)
    with pytest.raises(ParqError, match="unknown resize filter 'area'"):
        preprocess.prepare(image, K_LARGE, (160, 120), "area")


def test_the_second_point_sampling_grid_is_the_pixels_half_a_network_pixel_over():
    """Phase 0.5 of a 320x240 frame for 160x120 takes pixels (2u + 1, 2v + 1), none of phase
    0's, and its intrinsics project a point seen at such a pixel onto the network pixel that
    holds it."""
    rng = np.random.default_rng(4)
    image = rng.integers(0, 256, (240, 320, 3), dtype=np.uint8)
    first, _ = preprocess.prepare(image, K_LARGE, (160, 120), "point")
    second, K = preprocess.prepare(image, K_LARGE, (160, 120), "point", phase=0.5)
    np.testing.assert_array_equal(first, image[::2, ::2])
    np.testing.assert_array_equal(second, image[1::2, 1::2])
    for _ in range(20):
        u, v = rng.integers(0, 160), rng.integers(0, 120)
        point_camera = np.linalg.solve(K_LARGE, [2 * u + 1, 2 * v + 1, 1.0]) * rng.uniform(1, 5)
        np.testing.assert_allclose((K @ point_camera)[:2] / point_camera[2], [u, v],
                                   atol=1e-9)


def test_a_frame_has_a_second_grid_only_at_twice_the_network_size_with_point_sampling():
    assert preprocess.grids((320, 240), (160, 120), "point") == 2
    assert preprocess.grids((1296, 968), (160, 120), "point") == 2
    assert preprocess.grids((300, 240), (160, 120), "point") == 1
    assert preprocess.grids((160, 120), (160, 120), "point") == 1
    assert preprocess.grids((320, 240), (160, 120), preprocess.AUTHORS_FILTER) == 1
    small = np.zeros((120, 160, 3), np.uint8)
    with pytest.raises(ParqError, match="one sampling grid"):
        preprocess.prepare(small, K_LARGE / [[2], [2], [1]], (160, 120), "point", phase=0.5)
    with pytest.raises(ParqError, match="sampling phase 0.25"):
        preprocess.prepare(small, K_LARGE, (160, 120), "point", phase=0.25)
