"""The motion metric fitted to training sequences (bareesa.metric_fit, build-basis --metric fit)."""

import numpy as np
import pytest
import torch

from bareesa import basis_building, metric_fit, synthetic
from bareesa.errors import InputError
from bareesa.geodesics import decode_path, geodesic
from bareesa.h2_metric import PRESETS, H2Weights

#: The metric the training motions are geodesics of: far from both presets.
TRUE = H2Weights(1.0, 0.05, 0.0, 40.0, 4.0, 1e-3)


@pytest.fixture(scope="module")
def motions():
    """Six motions of a smooth sphere basis, each a geodesic of TRUE between random codes (7 frames)."""
    basis, _ = synthetic.smooth_sphere_basis(subdivisions=2, n_fields=5, seed=3, amplitude=0.15)
    t, f, h = basis.tensors()
    rng = np.random.default_rng(0)
    seqs = []
    for _ in range(6):
        a, b = rng.normal(scale=1.2, size=(2, basis.n_fields))
        path = geodesic(t, f, h, a, b, TRUE, steps=7, max_iter=400).path
        seqs.append(decode_path(t, h, path))
    return basis, seqs


def test_fit_recovers_a_metric_whose_geodesics_are_the_training_motions(motions):
    basis, seqs = motions
    built = basis_building.build_basis(basis.template, basis.faces, {"pose": seqs[:3], "more": seqs[3:]},
                                       {"pose": 5, "more": 5}, weights="fit")
    fit = built.provenance["metric_fit"]
    assert fit["chosen"] == "fit" and built.weights == H2Weights(*fit["fitted_weights"])
    scores = fit["held_out_frame_error"]
    # held-out frames are predicted better by the fit than by either preset, by a clear margin
    assert scores["fit"] < 0.5 * min(scores["body"], scores["face"])
    # the shape metric (registration, random bodies) stays the paper's
    assert built.shape_metric == PRESETS["body"]
    # geodesics of the fitted metric pass near the motions' middle frames; the presets' do not
    t, f, h = built.tensors()
    from bareesa.latent import project_to_basis

    def middle_error(w):
        errs = []
        for s in seqs:
            c = project_to_basis(built, s, ridge=0.0)[0]
            g = geodesic(t, f, h, c[0], c[-1], w, steps=7)
            errs.append(np.linalg.norm(decode_path(t, h, g.path[3:4])[0] - s[3], axis=1).mean())
        return np.mean(errs)

    assert middle_error(built.weights) < 0.5 * middle_error(PRESETS["body"])


def test_fit_needs_two_motions_and_build_basis_tells_so(motions):
    basis, seqs = motions
    assert basis_building.fits_metric({"pose": seqs[:2]}) and not basis_building.fits_metric({"pose": seqs[:1]})
    with pytest.raises(InputError, match="two training sequences"):
        metric_fit.choose_motion_metric(basis, seqs[:1])
    with pytest.raises(InputError, match="two training sequences"):
        metric_fit.choose_motion_metric(basis, [seqs[0], seqs[1][:2]])


def test_linearised_prediction_is_smallest_near_the_true_metric(motions):
    basis, seqs = motions
    codes = [np.asarray(c) for c in (basis_building_codes(basis, s) for s in seqs)]
    pairs = metric_fit._interior(codes, 100)
    terms = metric_fit._LocalTerms(basis, codes, pairs, metric_fit.Monitor("t"))
    true = terms.displacement(np.array(TRUE.as_tuple()))
    body = terms.displacement(np.array(PRESETS["body"].as_tuple()))
    assert true < 1e-6 * body and true < 1e-6 * terms.displacement(np.array(PRESETS["face"].as_tuple()))
    # the fit finds weights as good, and they are TRUE's (to the scale a0 = 1)
    fitted = terms.fit()
    assert terms.displacement(np.array(fitted.as_tuple())) < 1e-6 * body
    for got, want in zip(fitted.as_tuple(), TRUE.as_tuple()):
        assert got == pytest.approx(want, rel=0.05, abs=5e-3)


def basis_building_codes(basis, seq):
    from bareesa.latent import project_to_basis

    return project_to_basis(basis, seq, ridge=0.0)[0]
