import json

import numpy as np
import pytest
import torch

from bareesa import basis_building, basis_io, geometry, h2_metric, latent, statistics, synthetic
from bareesa.errors import InputError
from tests.solver.support import small_basis


def test_decoder_matches_direct_sum():
    b = small_basis()
    t, f, h = b.tensors()
    alpha = torch.tensor([[0.3, -1.0, 0.5, 2.0], [0.0, 0.1, 0.0, -0.2]], dtype=torch.float64)
    out = latent.decode(t, h, alpha)
    for k in range(2):
        direct = t + sum(alpha[k, i] * h[i] for i in range(4))
        assert torch.allclose(out[k], direct, rtol=1e-13, atol=1e-13)


def test_latent_metric_is_pullback_of_h2_metric():
    b = small_basis()
    t, f, h = b.tensors()
    alpha = torch.tensor([0.3, -1.0, 0.5, 2.0], dtype=torch.float64)
    gbar = latent.latent_metric(t, f, h, alpha, b.weights)
    q = latent.decode(t, h, alpha)
    beta = torch.tensor([1.0, 0.5, -2.0, 0.25], dtype=torch.float64)
    direct = h2_metric.squared_norm(q, f, torch.tensordot(beta, h, dims=1), b.weights)
    assert torch.isclose(beta @ gbar @ beta, direct, rtol=1e-12)
    assert torch.isclose(gbar[1, 2], h2_metric.inner_product(q, f, h[1], h[2], b.weights), rtol=1e-12)


def test_latent_path_energy_equals_sum_of_metric_matrix_quadratic_forms():
    b = small_basis()
    t, f, h = b.tensors()
    path = torch.tensor(np.random.default_rng(2).normal(size=(4, 4)) * 0.3)
    e = latent.latent_path_energy(t, f, h, path, b.weights)
    direct = 0
    for k in range(3):
        d = path[k + 1] - path[k]
        direct = direct + d @ latent.latent_metric(t, f, h, (path[k] + path[k + 1]) / 2, b.weights) @ d * 3
    assert torch.isclose(e, direct, rtol=1e-10)


def test_basis_save_load_roundtrip_keeps_everything(tmp_path):
    b = small_basis()
    b.extras["gmm_means"] = np.arange(6.0).reshape(2, 3)
    basis_io.save_basis(tmp_path / "b.npz", b)
    card = json.loads((tmp_path / "b.json").read_text())
    assert card["n_fields"] == 4 and card["groups"] == {"pose": [0, 3], "shape": [3, 4]}
    c = basis_io.load_basis(tmp_path / "b.npz")
    assert np.array_equal(c.template, b.template) and np.array_equal(c.faces, b.faces)
    assert np.array_equal(c.fields, b.fields)
    assert c.groups == b.groups and c.weights == b.weights and c.schedule == b.schedule
    assert c.scale == 2.0 and c.name == "small"
    assert np.array_equal(c.extras["gmm_means"], b.extras["gmm_means"])
    assert c.group_slice("shape") == slice(3, 4)


def test_basis_validation_errors_are_precise(tmp_path):
    v, f = synthetic.blob_mesh(1)
    h = np.zeros((2,) + v.shape)
    with pytest.raises(InputError, match="non-finite"):
        latent.Basis(template=v, faces=f, fields=np.full_like(h, np.nan), groups={})
    with pytest.raises(InputError, match="fields must be"):
        latent.Basis(template=v, faces=f, fields=h[:, :-1], groups={})
    with pytest.raises(InputError, match="group 'pose'"):
        latent.Basis(template=v, faces=f, fields=h, groups={"pose": (0, 5)})
    with pytest.raises(InputError, match="exactly once"):
        latent.Basis(template=v, faces=f, fields=h, groups={"pose": (0, 1)})
    with pytest.raises(InputError, match="face indices"):
        latent.Basis(template=v, faces=f + 100, fields=h, groups={})
    with pytest.raises(InputError, match="does not exist"):
        basis_io.load_basis(tmp_path / "missing.npz")
    with pytest.raises(InputError, match="no bundled basis named"):
        basis_io.load_basis("no-such-basis")
    (tmp_path / "junk.npz").write_bytes(b"not a zip")
    with pytest.raises(InputError, match="cannot read"):
        basis_io.load_basis(tmp_path / "junk.npz")


def test_build_basis_recovers_span_of_generating_motions():
    b = small_basis(p=3)
    t = b.template
    pose_dirs, shape_dir = b.fields[:2], b.fields[2]
    rng = np.random.default_rng(0)
    seqs = [t + np.cumsum(rng.normal(size=(6, 2)), 0)[:, :, None, None].__mul__(pose_dirs[None]).sum(1)
            for _ in range(3)]
    ids = [t + c * shape_dir for c in (0.0, 1.0, -0.5, 2.0)]
    built = basis_building.build_basis(t, b.faces, {"pose": seqs, "shape": [np.stack(ids)]}, {"pose": 5, "shape": 3})
    assert built.groups == {"pose": (0, 2), "shape": (2, 3)}  # rank-limited: 2 pose and 1 shape direction
    rep = built.provenance["groups"]
    assert rep["pose"]["explained_variance"] == pytest.approx(1.0)
    assert rep["pose"]["tangent_vectors"] == 15
    span = built.fields.reshape(3, -1)
    q, _ = np.linalg.qr(span.T)
    for d in list(pose_dirs) + [shape_dir]:
        d = d.ravel()
        assert np.linalg.norm(d - q @ (q.T @ d)) < 1e-8 * np.linalg.norm(d)


def test_build_basis_rejects_frames_in_another_topology():
    b = small_basis()
    with pytest.raises(InputError, match="registered to the template"):
        basis_building.build_basis(b.template, b.faces, {"pose": [np.zeros((3, 5, 3))]}, {"pose": 2})
    with pytest.raises(InputError, match="do not move"):
        basis_building.build_basis(b.template, b.faces, {"pose": [np.stack([b.template] * 3)]}, {"pose": 2})


def test_principal_fields_keep_the_rank_and_drop_float32_rounding_noise():
    rng = np.random.default_rng(0)
    directions = rng.normal(size=(3, 50, 3))
    tangents = np.tensordot(rng.normal(size=(40, 3)), directions, axes=1)
    noisy = tangents.astype(np.float32).astype(np.float64)  # frames baked in float32
    fields, ratios = basis_building.principal_fields(noisy, 10)
    assert fields.shape == (3, 50, 3) and np.isclose(ratios.sum(), 1.0)
    # the fields span the true directions
    coef, *_ = np.linalg.lstsq(fields.reshape(3, -1).T, directions.reshape(3, -1).T, rcond=None)
    residual = directions.reshape(3, -1).T - fields.reshape(3, -1).T @ coef
    assert np.abs(residual).max() < 1e-5


def test_whitening_makes_the_metric_the_identity_and_time_whitening_the_path_energy():
    rng = np.random.default_rng(1)
    a = rng.normal(size=(5, 5))
    gram = a @ a.T + 1e-3 * np.eye(5)
    b = latent.whitening(gram)
    assert np.allclose(b @ gram @ b.T, np.eye(5), atol=1e-9)
    r_inv = latent.time_whitening(4)
    k = 2 * np.eye(4) - np.eye(4, k=1) - np.eye(4, k=-1)
    assert np.allclose(r_inv.T @ k @ r_inv, np.eye(4), atol=1e-12)
    with pytest.raises(InputError, match="positive definite"):
        latent.whitening(-gram)


def test_template_metric_is_cached_saved_and_recomputed_for_other_weights(tmp_path):
    b, _ = synthetic.smooth_sphere_basis(subdivisions=1, n_fields=3)
    t, f, h = b.tensors()
    g = b.template_metric()
    assert np.allclose(g, latent.latent_metric(t, f, h, torch.zeros(3, dtype=torch.float64), b.weights).numpy())
    basis_io.save_basis(tmp_path / "b.npz", b)
    loaded = basis_io.load_basis(tmp_path / "b.npz")
    assert np.array_equal(loaded.extras["template_metric"], g) and loaded.template_metric() is loaded.extras[
        "template_metric"]
    other = loaded.template_metric((2, 1, 1, 1, 1, 5))
    assert not np.allclose(other, g)


def test_projection_ridge_keeps_rough_tiny_directions_small_and_the_fit_close():
    from dataclasses import replace

    from bareesa.latent import project_to_basis

    basis, _ = synthetic.smooth_sphere_basis(subdivisions=2, n_fields=6, seed=0)
    # a seventh field of tiny, rough displacements: small in L2, large in the H2 metric (like the
    # low-variance tail of a PCA basis); least squares uses it to fit noise
    rng = np.random.default_rng(1)
    rough = 1e-3 * rng.normal(size=basis.fields[0].shape)
    basis = replace(basis, fields=np.concatenate([basis.fields, rough[None]]), groups={"all": (0, 7)}, extras={})
    alpha = np.array([0.5, -0.3, 0.2, 0.1, -0.4, 0.3, 0.0])
    exact = basis.template + np.tensordot(alpha, basis.fields, axes=1)
    noisy = exact + 2e-3 * rng.normal(size=exact.shape) + 0.5 * rough
    plain, rms_plain = project_to_basis(basis, noisy, ridge=0)
    ridged, rms_ridged = project_to_basis(basis, noisy, ridge=0.05)
    default, rms_default = project_to_basis(basis, noisy)
    assert abs(plain[6]) > 0.3 and abs(ridged[6]) < 0.5 * abs(plain[6])  # the rough field is damped
    assert abs(ridged[6]) < abs(default[6]) < abs(plain[6])  # the default ridge damps less
    assert np.allclose(ridged[:6], alpha[:6], atol=0.05) and np.allclose(default[:6], alpha[:6], atol=0.01)
    assert rms_default < rms_plain + 1e-3 and rms_ridged < 3 * rms_plain  # the default barely changes the fit
    code, rms = project_to_basis(basis, exact, ridge=0)
    assert rms < 1e-9 and np.allclose(code, alpha)
    # a batch projects each mesh as alone
    codes, rms_batch = project_to_basis(basis, np.stack([noisy, exact]))
    alone = project_to_basis(basis, exact)
    assert codes.shape == (2, 7) and np.allclose(codes, [default, alone[0]])
    assert np.allclose(rms_batch, [rms_default, alone[1]])
    with pytest.raises(InputError, match="vertices"):
        project_to_basis(basis, exact[:-1])
    with pytest.raises(InputError, match="ridge"):
        project_to_basis(basis, exact, ridge=-1.0)
    with pytest.raises(InputError, match="NaN"):
        project_to_basis(basis, np.full_like(exact, np.nan))
    # the ridge's metric: the basis' own by default, any weights when asked (a registration's shape metric)
    other = h2_metric.H2Weights(1.0, 1e3, 0.0, 1e2, 0.0, 1e-2)
    area = geometry.vertex_areas(torch.as_tensor(basis.template), torch.as_tensor(basis.faces)).numpy()
    a = basis.fields.reshape(7, -1).T
    gram = (a * np.repeat(area, 3)[:, None]).T @ a
    metric = basis.template_metric(other)
    manual = np.linalg.solve(gram + 0.05 * np.trace(gram) / np.trace(metric) * metric,
                             (a * np.repeat(area, 3)[:, None]).T @ (noisy - basis.template).ravel())
    weighted, _ = project_to_basis(basis, noisy, ridge=0.05, weights=other)
    assert np.allclose(weighted, manual) and not np.allclose(weighted, ridged, atol=1e-3)
    assert np.allclose(project_to_basis(basis, noisy, ridge=0.05, weights=basis.weights)[0], ridged)


def test_off_basis_detail_carried_along_reproduces_the_keyframes_and_the_vertex_blend():
    from bareesa.latent import detail_along, off_basis_detail, project_to_basis

    b = small_basis()
    t, _, h = b.tensors()
    rng = np.random.default_rng(2)
    # two meshes off the span of the basis: codes miss a random bump each
    alpha = np.array([[0.3, -0.5, 0.2, 0.4], [-0.2, 0.6, 0.1, -0.3]])
    meshes = b.template + np.tensordot(alpha, b.fields, axes=1) + 0.02 * rng.normal(size=(2, *b.template.shape))
    codes = project_to_basis(b, meshes)[0]
    detail = off_basis_detail(b, meshes, codes)
    assert detail.shape == meshes.shape and np.sqrt((detail ** 2).sum(-1).mean()) > 0.01
    decoded = latent.decode(t, h, torch.as_tensor(codes)).numpy()
    assert np.allclose(decoded + detail, meshes, atol=1e-12)  # F(code) + detail is the mesh
    assert np.allclose(off_basis_detail(b, meshes[1], codes[1]), detail[1])  # one mesh as in the batch
    # along the straight latent line, interpolating (0..1) and continuing (2, 3), the carried
    # detail turns F into exactly the vertex blend of the two meshes
    times = np.array([0.0, 0.25, 0.5, 1.0, 2.0, 3.0])
    line = codes[0] + times[:, None] * (codes[1] - codes[0])
    frames = latent.decode(t, h, torch.as_tensor(line)).numpy() + detail_along(detail[0], detail[1], times)
    blend = meshes[0] + times[:, None, None] * (meshes[1] - meshes[0])
    assert np.allclose(frames, blend, atol=1e-12)
    with pytest.raises(InputError, match="vertices"):
        off_basis_detail(b, meshes[0][:-1], codes[0])
    with pytest.raises(InputError, match="do not match"):
        off_basis_detail(b, meshes, codes[0])
    with pytest.raises(InputError, match="two"):
        detail_along(detail[0], detail[1][:-1], times)


def test_shape_weights_are_saved_and_registration_and_random_bodies_use_them(tmp_path, monkeypatch):
    """A basis may measure shapes from the template (registration's regularizer, random bodies) with
    other H2 weights than its motion paths use (``human`` does): they travel in the card, registration
    and random bodies take them by default, geodesics keep ``weights``, and their template metric does
    not replace the stored one of the basis' own weights."""
    from bareesa import workflows
    from bareesa.h2_metric import PRESETS, H2Weights
    from bareesa.registration import multiscale

    b, _ = synthetic.smooth_sphere_basis(subdivisions=1, n_fields=3)
    assert b.shape_weights is None and b.shape_metric == b.weights
    b.shape_weights = H2Weights(2, 1, 1, 1, 1, 5)
    g = b.template_metric()
    basis_io.save_basis(tmp_path / "b.npz", b)
    loaded = basis_io.load_basis(tmp_path / "b.npz")
    assert loaded.shape_metric == H2Weights(2, 1, 1, 1, 1, 5) and loaded.weights == b.weights
    assert json.loads((tmp_path / "b.json").read_text())["shape_metric"] == [2, 1, 1, 1, 1, 5]
    other = loaded.template_metric(loaded.shape_weights)
    assert not np.allclose(other, g) and loaded.template_metric() is loaded.extras["template_metric"]
    assert loaded.template_metric(loaded.shape_weights) is other  # kept for the next registration
    # ... in the extras, so a basis saved afterwards carries it, and a process that loads it computes neither
    assert loaded.extras["shape_template_metric"] is other
    basis_io.save_basis(tmp_path / "c.npz", loaded)
    again = basis_io.load_basis(tmp_path / "c.npz")
    with monkeypatch.context() as patch:
        patch.setattr(latent.h2_metric, "assembled_metric_matrix", lambda *a, **k: pytest.fail("recomputed"))
        assert np.array_equal(again.template_metric(again.shape_weights), other)
        assert np.array_equal(again.template_metric(), g)
    assert not np.allclose(again.template_metric((3, 1, 1, 1, 1, 5)), other)  # other weights: computed
    again.extras["shape_template_metric"] = other[:2]  # a damaged one too
    assert np.allclose(again.template_metric(again.shape_weights), other, rtol=1e-12, atol=0)

    class Seen(Exception):
        pass

    def fake_problem(basis, sv, sf, config, *rest):
        raise Seen(config.shape_metric(basis))

    def fake_shoot(template, faces, fields, alpha0, velocity, weights, *args, **kwargs):
        raise Seen(weights)

    monkeypatch.setattr(multiscale, "RegistrationProblem", fake_problem)
    monkeypatch.setattr(workflows.shooting, "shoot", fake_shoot)
    loaded.extras.update(statistics.fit_distribution(np.random.default_rng(0).normal(size=(6, 3)), loaded.groups,
                                                     {g: 1 for g in loaded.groups}))
    for given, expected in ((None, H2Weights(2, 1, 1, 1, 1, 5)), ("body", PRESETS["body"])):
        with pytest.raises(Seen) as seen:
            multiscale.register(loaded, loaded.template, loaded.faces, prealign=False, metric=given)
        assert seen.value.args[0] == expected
        with pytest.raises(Seen) as seen:
            workflows.random_bodies(loaded, 1, seed=0, options=workflows.Options(weights=given))
        assert seen.value.args[0] == expected
        assert workflows.Options(weights=given).metric(loaded) == (loaded.weights if given is None else expected)
