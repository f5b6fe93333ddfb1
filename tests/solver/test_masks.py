"""Ignore masks (bareesa.masks): per-vertex ignore weights from files, and the face weights registration takes."""

import numpy as np
import pytest

from bareesa.errors import InputError
from bareesa.masks import face_weights_from_ignore, read_face_weights, read_ignore_weights


def test_text_masks_take_spaces_commas_lines_and_comments_like_the_npy_file(tmp_path):
    values = np.array([0.0, 1.0, 0.25, 0.5, 1.0])
    (tmp_path / "m.txt").write_text("# ignore weights\n0, 1\n0.25 0.5  # a comment\n1\n")
    np.save(tmp_path / "m.npy", values)
    np.testing.assert_array_equal(read_ignore_weights(tmp_path / "m.txt", 5), values)
    np.testing.assert_array_equal(read_ignore_weights(tmp_path / "m.npy", 5), values)
    (tmp_path / "words.txt").write_text("0 1 floor 0 0\n")
    with pytest.raises(InputError, match="cannot read the mask"):
        read_ignore_weights(tmp_path / "words.txt", 5)
    np.save(tmp_path / "bool.npy", values >= 0.5)  # a selection saved as it is
    np.testing.assert_array_equal(read_ignore_weights(tmp_path / "bool.npy", 5), [0, 1, 0, 1, 1])
    np.save(tmp_path / "flat.npy", values.reshape(5, 1))
    with pytest.raises(InputError, match=r"expected 5 numbers.*shape \(5, 1\)"):
        read_ignore_weights(tmp_path / "flat.npy", 5)


def test_a_face_weighs_one_minus_its_vertices_mean_ignore_as_in_the_add_on():
    faces = np.array([[0, 1, 2], [1, 2, 3], [2, 3, 4]])
    ignore = np.array([0.0, 0.0, 0.0, 1.0, 0.5])
    np.testing.assert_allclose(face_weights_from_ignore(ignore, faces), [1.0, 2 / 3, 0.5])


def test_a_mask_that_ignores_every_face_is_refused_though_some_vertices_are_kept(tmp_path):
    faces = np.array([[0, 1, 2]])
    np.save(tmp_path / "m.npy", np.array([1.0, 1.0, 1.0, 0.0]))  # vertex 3 is in no face
    with pytest.raises(InputError, match="ignores every face"):
        read_face_weights(tmp_path / "m.npy", faces, 4)
