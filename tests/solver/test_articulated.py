"""The articulated pre-fit: a basis' skeleton posed by linear blend skinning, its pose found from rest and
handed to the latent levels, so that a pose far from every training pose is registered."""

import dataclasses

import numpy as np
import pytest
import torch

from bareesa import registration, synthetic
from bareesa.latent import Level
from bareesa.registration import articulated
from bareesa.registration.config import ArticulatedFit
from bareesa.transforms import Similarity

#: a knee raised and turned out with the foot folded back (a tree pose's leg) and both arms raised high:
#: every joint past the training poses' 60 degrees
FAR_POSE = {"hip.L": (-100, 0, 40), "knee.L": (120, 0, 0), "shoulder.L": (0, -160, 0), "shoulder.R": (0, 150, 0)}
SCHEDULE = (Level(0.2, 1e7, 1, 60), Level(0.08, 1e9, 2, 80), Level(0.04, 1e11, 2, 80))


@pytest.fixture(scope="module")
def figure():
    return synthetic.articulated_figure_basis(schedule=SCHEDULE)


def test_skinning_at_rest_is_the_template_and_a_joint_moves_its_subtree_rigidly(figure):
    basis, posed = figure
    skeleton = articulated.Skeleton.of_basis(basis)
    assert np.allclose(posed(np.zeros((len(skeleton.joints), 3))), basis.template, atol=1e-12)
    bent = posed(synthetic.figure_pose({"hip.L": (-90, 0, 0)}))
    names = [n for n, *_ in synthetic.FIGURE_JOINTS]
    moved = np.linalg.norm(bent - basis.template, axis=1) > 1e-9
    leg = skeleton.weights[:, [names.index("hip.L"), names.index("knee.L")]].sum(1) > 0
    assert np.array_equal(moved, leg)  # the thigh and the shin follow the hip, nothing else moves
    knee = skeleton.joints[names.index("knee.L")]
    hip = skeleton.joints[names.index("hip.L")]
    thigh = skeleton.weights[:, names.index("hip.L")] > 0
    # rigid: distances to the hip kept; the knee, 0.4 m below the hip, now 0.4 m in front of it (-y)
    assert np.allclose(np.linalg.norm(bent[thigh] - hip, axis=1), np.linalg.norm(basis.template[thigh] - hip, axis=1))
    rotation = articulated.batch_rotations(torch.as_tensor(np.radians([[-90.0, 0.0, 0.0]])))[0].numpy()
    assert np.allclose(rotation @ (knee - hip) + hip, hip + [0.0, -0.4, 0.0], atol=1e-12)


def test_a_skeleton_is_read_from_the_basis_and_a_damaged_one_is_ignored(figure):
    basis, _ = figure
    assert articulated.Skeleton.of_basis(basis).names[3] == "hip.L"
    assert articulated.Skeleton.of_basis(dataclasses.replace(basis, extras={})) is None
    broken = dict(basis.extras, skeleton_parents=np.array([0, 0, 0, 0, 3, 0, 5]))  # the root its own parent
    assert articulated.Skeleton.of_basis(dataclasses.replace(basis, extras=broken)) is None
    reversed_range = dict(basis.extras, skeleton_limits=basis.extras["skeleton_limits"][..., ::-1])
    assert articulated.Skeleton.of_basis(dataclasses.replace(basis, extras=reversed_range)) is None


def test_the_far_pose_is_found_from_rest_by_the_articulated_fit(figure):
    basis, posed = figure
    truth = posed(synthetic.figure_pose(FAR_POSE))
    scan = synthetic.remesh_same_surface(truth, basis.faces, seed=1)
    fit = articulated.fit_pose(articulated.Skeleton.of_basis(basis), basis, *scan, [Similarity()], ArticulatedFit())
    found = fit.transform.invert(fit.posed)
    assert np.linalg.norm(found - truth, axis=1).mean() < 0.04  # 4 cm on a 1.5 m figure: a start
    rest = articulated.fit_pose(articulated.Skeleton.of_basis(basis), basis, *scan, [Similarity()],
                                ArticulatedFit(max_iter=0))  # the search alone, no descent: already close
    assert np.linalg.norm(rest.transform.invert(rest.posed) - truth, axis=1).mean() < 0.1


def test_a_pose_never_in_training_registers_with_the_articulated_stage_and_not_without(figure):
    basis, posed = figure
    truth = posed(synthetic.figure_pose(FAR_POSE))
    scan = synthetic.remesh_same_surface(truth, basis.faces, seed=1)
    names = [n for n, *_ in synthetic.FIGURE_JOINTS]
    foot = np.argmin(np.where(basis.extras["skinning_weights"][:, names.index("knee.L")] > 0,
                              basis.template[:, 2], np.inf))  # the left shin's lowest vertex
    res = registration.register(basis, *scan)
    assert res.articulated is not None and res.articulated["seconds"] > 0
    assert np.linalg.norm(res.vertices - truth, axis=1).mean() < 0.1
    assert np.linalg.norm(res.vertices[foot] - truth[foot]) < 0.15  # the folded foot is where it is
    # after the posed start only the levels no coarser than the articulated fit's sigmas run
    kept = sum(level.sigma <= max(ArticulatedFit().sigmas) for level in SCHEDULE)
    assert len(res.levels) == kept < len(SCHEDULE)
    coarse = registration.register(basis, *scan, **{"articulated.coarse_levels": True})
    assert len(coarse.levels) == len(SCHEDULE) and coarse.articulated["score"] is not None
    plain = registration.register(basis, *scan, **{"articulated.enabled": False})
    assert plain.articulated is None
    plain_error, error = (np.linalg.norm(r.vertices - truth, axis=1).mean() for r in (plain, res))
    assert plain_error > 3 * error


def test_a_scan_near_rest_skips_the_search_and_a_far_one_does_not(figure):
    """With a pose library, a scan that rest fits better than every library pose is left to the latent
    levels (no search: its cost is saved); a far pose is searched."""
    basis, posed = figure
    library = synthetic.figure_pose(FAR_POSE)[None]
    with_library = dataclasses.replace(basis, extras=dict(basis.extras, skeleton_pose_library=library))
    skeleton = articulated.Skeleton.of_basis(with_library)
    near = posed(synthetic.figure_pose({"hip.L": (-10, 0, 0), "shoulder.R": (0, 10, 0)}))
    assert articulated.fit_pose(skeleton, with_library, near, basis.faces, [Similarity()], ArticulatedFit()) is None
    far = posed(synthetic.figure_pose(FAR_POSE))
    fit = articulated.fit_pose(skeleton, with_library, far, basis.faces, [Similarity()], ArticulatedFit())
    assert fit is not None and np.linalg.norm(fit.posed - far, axis=1).mean() < 0.03


def test_the_posed_start_is_projected_with_the_registrations_own_metric(figure, monkeypatch):
    """The articulated fit's skinned template enters the latent space through a ridge in the metric the
    latent levels' path energy uses (the registration's shape metric), not the basis' motion metric."""
    basis, posed = figure
    from bareesa.h2_metric import H2Weights
    from bareesa.registration import multiscale

    motion = H2Weights(1.0, 0.5, 5.0, 1.0, 0.1, 0.0)  # a motion metric unlike the shape metric
    basis = dataclasses.replace(basis, weights=motion, shape_weights=H2Weights.parse(basis.weights))
    seen = []
    real = articulated.project_to_basis

    def spy(b, verts, ridge, weights=None):
        seen.append(weights)
        return real(b, verts, ridge=ridge, weights=weights)

    monkeypatch.setattr(articulated, "project_to_basis", spy)
    scan = synthetic.remesh_same_surface(posed(synthetic.figure_pose(FAR_POSE)), basis.faces, seed=1)
    config = registration.RegistrationConfig.from_basis(basis).with_overrides(
        {"detail.enabled": False, "retry": False, "schedule": SCHEDULE[-1:]})
    res = multiscale.register(basis, *scan, config)
    assert res.articulated["score"] is not None
    assert seen and all(w == config.shape_metric(basis) for w in seen) and seen[0] != motion


def test_a_bone_below_a_searched_one_is_tried_only_at_the_librarys_rotations(figure):
    basis, _ = figure
    names = [n for n, *_ in synthetic.FIGURE_JOINTS]
    knee, hip = names.index("knee.L"), names.index("hip.L")
    library = np.zeros((3, len(names), 3))
    library[:, knee, 0] = np.radians([30, 80, 200])  # bent as a knee bends (the last past its range)
    skeleton = dataclasses.replace(articulated.Skeleton.of_basis(basis), library=library)
    tried = {}

    class Counting:  # records each joint's candidates; no candidate is better than where it is
        def __init__(self):
            self.skeleton, self.basis = skeleton, basis

        def rotations(self, x):
            return np.asarray(x[:3 * len(names)]).reshape(len(names), 3).copy()

        def values(self, sigma, x, trials):
            varying = np.flatnonzero(np.ptp(trials, axis=0).max(1) > 0)
            for j in varying:
                tried.setdefault(int(j), []).extend(trials[:, j].tolist())
            return np.ones(len(trials))

    articulated.direction_search(Counting(), 0.1, np.zeros(3 * len(names) + 7))
    allowed = np.clip(library[:, knee], skeleton.limits[knee, :, 0], skeleton.limits[knee, :, 1])
    assert np.allclose(sorted(map(tuple, tried[knee])), sorted(map(tuple, allowed)), atol=1e-6)
    assert len(tried[hip]) > 10  # a limb's root is tried toward the 26 directions too (clipped, some alike)
