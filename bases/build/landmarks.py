"""Named landmarks of the bundled templates, found by rules on the template's geometry.

Each rule set maps a template (N, 3), (F, 3) to {name: template vertex index}; the builders store
the result in the basis (``Basis.landmarks``, in its card), and
``python -m bases.build.landmarks [NAME ...]`` writes it into the shipped bases without rebuilding
them. Conventions of the human template: Z up, facing -Y, the body's left at +X, feet at z = 0,
arms hanging in Anny's rest pose; "_l"/"_r" are the body's left and right, and every right
landmark is the mirror image (x -> -x) of its left one.
"""

import argparse
import sys

import numpy as np

#: Lengths of the human rules, as shares of the body's height H.
MIDLINE = 0.004        # |x| below this is the sagittal midline
UPPER_ARM = 0.175      # shoulder tip -> elbow, along the arm
HAND = 0.105           # middle fingertip -> wrist
FOOT_HEEL_BAND = 0.02  # heel: the back-most point of the foot this close to the floor


def _unit(v):
    v = np.asarray(v, np.float64)
    return v / np.linalg.norm(v)


def _extreme(verts, mask, direction):
    """Index of the vertex of ``mask`` farthest along ``direction``."""
    idx = np.flatnonzero(mask)
    if idx.size == 0:
        raise ValueError("a landmark rule selected no vertex: the template does not look as the rule expects")
    return int(idx[np.argmax(verts[idx] @ _unit(direction))])


def _mirror(verts, i):
    """The vertex nearest the mirror image (x -> -x) of vertex i."""
    p = verts[i] * np.array([-1.0, 1.0, 1.0])
    return int(np.argmin(((verts - p) ** 2).sum(1)))


def _ring(verts, mask, centre, radius, width):
    """Vertices of ``mask`` at distance radius +- width/2 from centre."""
    d = np.linalg.norm(verts - centre, axis=1)
    return mask & (np.abs(d - radius) < width / 2)


def human_landmarks(verts, faces=None):
    """The human template's anatomical landmarks: (N, 3) -> {name: vertex}."""
    t = np.asarray(verts, np.float64)
    x, y, z = t.T
    h = z.max() - z.min()
    z0 = z.min()
    mid = np.abs(x) < MIDLINE * h
    marks = {}
    head = z > z0 + 0.87 * h
    nose = _extreme(t, mid & head, (0, -1, 0))
    marks["nose_tip"] = nose
    nz, ny = t[nose, 2], t[nose, 1]
    jaw = mid & (z < nz - 0.025 * h) & (z > nz - 0.055 * h) & (y < ny + 0.07 * h)
    marks["chin"] = _extreme(t, jaw, (0, -1, -1))  # the front-lower corner of the jaw's profile
    # ear: the lateral-most shell of the head between eye and jaw height, behind the face
    band = (x > 0) & (z > nz - 0.045 * h) & (z < nz + 0.03 * h) & (y > ny + 0.045 * h)
    shell = band & (x > x[band].max() - 0.008 * h)
    marks["ear_lobe_l"] = _extreme(t, shell, (0, 0, -1))
    left = x > 0
    upper = (z > z0 + 0.75 * h) & (z < z0 + 0.86 * h)
    marks["shoulder_tip_l"] = _extreme(t, left & upper & (x > 0.06 * h), (1, 0, 1))
    shoulder = t[marks["shoulder_tip_l"]]
    arm = left & (x > shoulder[0] - 0.01 * h) & (z < shoulder[2]) & (z > z0 + 0.45 * h)
    tip = int(np.flatnonzero(arm)[np.argmax(np.linalg.norm(t[arm] - shoulder, axis=1))])
    marks["middle_fingertip_l"] = tip
    elbow_ring = _ring(t, arm, shoulder, UPPER_ARM * h, 0.02 * h)
    centre = t[elbow_ring].mean(0)
    outside = _unit(centre - shoulder) + _unit(centre - t[tip])  # away from both bones: the back of the bend
    marks["elbow_l"] = _extreme(t, elbow_ring, outside)
    wrist_ring = _ring(t, arm, t[tip], HAND * h, 0.015 * h) & (np.linalg.norm(t - shoulder, axis=1)
                                                                 > UPPER_ARM * h * 1.5)
    marks["wrist_l"] = _extreme(t, wrist_ring, outside)
    # the navel is a pit: the front vertex near the midline lying farthest behind its surroundings
    belly = (np.abs(x) < 0.02 * h) & (z > z0 + 0.56 * h) & (z < z0 + 0.66 * h) & (y < 0)
    idx = np.flatnonzero(belly)
    depth = np.full(len(idx), -np.inf)
    for k, i in enumerate(idx):
        r = np.linalg.norm(t[idx] - t[i], axis=1)
        around = idx[(r > 0.009 * h) & (r < 0.018 * h)]
        if around.size:
            depth[k] = y[i] - y[around].mean()
    marks["navel"] = int(idx[np.argmax(depth)])
    leg = left & (z < z0 + 0.45 * h) & (z > z0 + 0.06 * h) & (x < 0.16 * h)
    knee_band = leg & (np.abs(z - (z0 + 0.28 * h)) < 0.01 * h)
    marks["knee_l"] = _extreme(t, knee_band, (0, -1, 0))  # the front of the knee (patella)
    foot = left & (z < z0 + 0.06 * h)
    ankle_band = left & (np.abs(z - (z0 + 0.045 * h)) < 0.006 * h) & (x < 0.16 * h)
    marks["ankle_l"] = _extreme(t, ankle_band, (1, 0, 0))
    marks["heel_l"] = _extreme(t, foot & (z < z0 + FOOT_HEEL_BAND * h), (0, 1, -0.2))
    toes = foot & (z < z0 + 0.03 * h)
    marks["big_toe_tip_l"] = _extreme(t, toes, (-0.25, -1, 0))
    for name in [n for n in marks if n.endswith("_l")]:
        marks[name[:-2] + "_r"] = _mirror(t, marks[name])
    return marks


def deformables_landmarks(verts, faces=None):
    """The capsule's two ends and a point of its seam (the +X line at mid-length): (N, 3) -> {name: vertex}."""
    t = np.asarray(verts, np.float64)
    r = np.abs(t[:, 0]).max()
    return {"top_end": int(np.argmax(t[:, 2])), "bottom_end": int(np.argmin(t[:, 2])),
            "seam": int(np.argmin(((t - [r, 0.0, 0.0]) ** 2).sum(1)))}


#: Landmark rules of each bundled basis.
LANDMARK_RULES = {"human": human_landmarks, "deformables": deformables_landmarks}
#: What the card says of them (``provenance["landmarks"]``).
LANDMARK_NOTES = {
    "human": "template vertices found by bases/build/landmarks.py (human_landmarks) on the rest template: "
             "_l/_r are the body's left (+X) and right, mirror images; elbow = back of the elbow, knee = "
             "front of the knee, ankle = outer ankle bone, wrist = back of the wrist",
    "deformables": "template vertices found by bases/build/landmarks.py (deformables_landmarks): the capsule's "
                   "two poles (top_end at +Z) and the seam, the +X side at mid-length"}


def main(argv=None):
    """Write the rules' landmarks into shipped bases (their cards), leaving the arrays unchanged."""
    from bareesa.basis_io import load_basis, update_card

    parser = argparse.ArgumentParser(prog="python -m bases.build.landmarks", description=main.__doc__)
    parser.add_argument("names", nargs="*", default=sorted(LANDMARK_RULES), help="bases (default: all with rules)")
    args = parser.parse_args(argv)
    for name in args.names:
        if name not in LANDMARK_RULES:
            parser.error(f"no landmark rules for '{name}' (rules: {', '.join(sorted(LANDMARK_RULES))})")
        basis = load_basis(name)
        marks = LANDMARK_RULES[name](basis.template, basis.faces)
        update_card(name, landmarks=marks, provenance=basis.provenance | {"landmarks": LANDMARK_NOTES[name]})
        print(f"{name}: {len(marks)} landmarks: {', '.join(marks)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
