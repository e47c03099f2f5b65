"""The head fitter recovers expression weights, gaze, head pose and identity of the bundled ICT head
from its landmarks: projected through the shipped correspondence (with noise and outliers), and seen by
MediaPipe on renders."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from meshsplat.drivers.blendshape import BlendshapeDriver, axis_angle_to_matrix
from meshsplat.errors import MeshsplatError
from meshsplat.track.head_fit import MIN_FRAMES_FOR_IDENTITY, _identity_basis, fit_head
from meshsplat.track.head_render import render_head
from meshsplat.track.ict_head import NUM_LANDMARKS, load_ict_head
from meshsplat.track.tracker_camera import focal_from_fov

W = H = 512
T = 40
SHOWN = ("jawOpen", "mouthSmile_L", "mouthSmile_R", "eyeBlink_L", "eyeBlink_R", "browInnerUp_L", "browInnerUp_R")


@pytest.fixture(scope="module")
def head():
    return load_ict_head()


def _clip(head, frames: int = T):
    """A smooth clip: the jaw opening to 0.7, smiles, blinks and brows, the gaze wandering +-15 degrees,
    the head turning to 35 degrees and nodding, a person a little unlike the ICT neutral."""
    s = torch.linspace(0, 1, frames)
    E = len(head.names)
    w = torch.zeros(frames, E)
    wave = lambda f, p=0.0: (1 - torch.cos(2 * math.pi * f * s + p)) / 2  # noqa: E731
    w[:, head.names.index("jawOpen")] = 0.7 * wave(1.0)
    w[:, head.names.index("mouthSmile_L")] = 0.6 * wave(0.7, 1.0)
    w[:, head.names.index("mouthSmile_R")] = 0.5 * wave(0.7, 1.3)
    w[:, head.names.index("eyeBlink_L")] = 0.8 * wave(1.5, 2.0)
    w[:, head.names.index("eyeBlink_R")] = 0.8 * wave(1.5, 2.0)
    w[:, head.names.index("browInnerUp_L")] = 0.6 * wave(0.5, 3.0)
    w[:, head.names.index("browInnerUp_R")] = 0.6 * wave(0.5, 3.0)
    gaze = torch.zeros(frames, 2, 2)
    gaze[:, :, 0] = math.radians(15) * torch.sin(2 * math.pi * 0.8 * s)[:, None]
    gaze[:, :, 1] = math.radians(10) * torch.sin(2 * math.pi * 0.6 * s + 1)[:, None]
    rot = torch.stack(
        [
            math.radians(8) * torch.sin(2 * math.pi * 0.9 * s),
            math.radians(35) * torch.sin(math.pi * s),  # 0 -> 35 degrees -> 0
            math.radians(4) * torch.sin(2 * math.pi * 0.5 * s),
        ],
        1,
    )
    trans = torch.stack([2 * torch.sin(2 * math.pi * s), -1 + 0 * s, -58 - 3 * s], 1)
    coeffs = torch.zeros(19, 3)
    coeffs[0, 0], coeffs[1, 1], coeffs[5, 2], coeffs[4, 0] = 0.4, -0.3, 0.3, 0.2  # wider, shorter face, ...
    identity = _identity_basis(head.neutral) @ coeffs
    return identity, w, gaze, rot, trans


def _landmarks(head, identity, w, gaze, rot, trans, noise=0.5, outliers=4, seed=0, focal=None):
    f = focal_from_fov(W, H) if focal is None else focal
    pts = head.landmarks(head.pose(identity, w, gaze, rot, trans))
    cam = pts * torch.tensor([1.0, -1.0, -1.0])
    px = f * cam[..., :2] / cam[..., 2:] + torch.tensor([W / 2, H / 2])
    g = torch.Generator().manual_seed(seed)
    px = px + noise * torch.randn(px.shape, generator=g)
    for t in range(px.shape[0]):  # a few landmarks per frame far off, as a landmarker's bad points
        bad = torch.randperm(NUM_LANDMARKS, generator=g)[:outliers]
        px[t, bad] += 40 * torch.randn(outliers, 2, generator=g)
    return torch.cat([px, torch.zeros(px.shape[0], NUM_LANDMARKS, 1)], -1)  # MediaPipe's z column rides along


def _angle_deg(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    R = axis_angle_to_matrix(a) @ axis_angle_to_matrix(b).transpose(-1, -2)
    cos = ((R.diagonal(dim1=-2, dim2=-1).sum(-1) - 1) / 2).clamp(-1, 1)
    return torch.rad2deg(torch.acos(cos))


@pytest.fixture(scope="module")
def fitted(head):
    truth = _clip(head)
    fit = fit_head(_landmarks(head, *truth), W, H, fps=30.0)
    return truth, fit


def fit_landmarks(head, fitted):
    return _landmarks(head, *fitted[0])[..., :2]


def test_fit_recovers_pose_expressions_gaze(head, fitted):
    (_, w, gaze, rot, _), fit = fitted
    assert fit.weights.shape == (T, 57) and fit.names == head.names
    # reprojection: noise 0.5 px (its mean norm is 0.63 px) and 4 outliers of 478 per frame
    inliers = fit.landmark_error_px.median(1).values
    assert float(inliers.max()) < 1.0, inliers
    # head pose within 2 degrees, including the 35 degree turn
    err = _angle_deg(fit.rotations, rot)
    assert float(err.max()) < 2.0, err
    assert float(_angle_deg(fit.rotations[T // 2 : T // 2 + 1], rot[T // 2 : T // 2 + 1])[0]) < 2.0
    # the shapes landmarks show: within 0.1 on average, the jaw within 0.1 in every frame
    for name in SHOWN:
        i = head.names.index(name)
        assert float((fit.weights[:, i] - w[:, i]).abs().mean()) < 0.1, name
    jaw = head.names.index("jawOpen")
    assert float((fit.weights[:, jaw] - w[:, jaw]).abs().max()) < 0.1
    assert float(fit.weights[w[:, jaw].argmax(), jaw]) > 0.6  # the open mouth is seen as open
    # gaze within 3 degrees (mean), 6 degrees in any frame
    gerr = torch.rad2deg((fit.gaze - gaze).abs())
    assert float(gerr.mean()) < 3.0 and float(gerr.max()) < 6.0, gerr.max()


def test_fit_vertices_match_the_camera(head, fitted):
    (identity, w, gaze, rot, trans), fit = fitted
    cam = fit.camera()
    assert torch.equal(cam.viewmat, torch.diag(torch.tensor([1.0, -1.0, -1.0, 1.0])))
    t = T // 2
    v = fit.vertices(t)
    assert v.shape == head.neutral.shape and torch.allclose(v, fit.vertices()[t], atol=1e-4)
    # the reported error is that of the returned head (the fit poses the landmarks alone, about another pivot)
    err = (fit.project(head.landmarks(fit.vertices())) - fit_landmarks(head, fitted)).norm(dim=-1)
    assert torch.allclose(err, fit.landmark_error_px, atol=1e-3)
    truth = head.pose(identity, w[t : t + 1], gaze[t : t + 1], rot[t : t + 1], trans[t : t + 1])[0]
    # the whole head (mouth, back of the head) lands where the truth does, in pixels
    px, _ = cam.project(v)
    px_true, _ = cam.project(truth)
    face = torch.isin(torch.arange(len(v)), head.faces[head.face_material == head.material_names.index("M_Face")])
    assert float((px - px_true).norm(dim=1)[face].median()) < 1.5
    # BlendshapeDriver poses the fitted identity the same way (gaze aside: compare off the eyeballs)
    drv = BlendshapeDriver(fit.neutral, fit.faces, head.deltas, weights=fit.weights, rotations=fit.rotations)
    drv.set_sequence(fit.weights, fit.rotations, fit.translations)
    eyes = torch.isin(torch.arange(len(v)), torch.cat(head.eye_vertices))
    assert torch.allclose(drv.vertices(t)[~eyes], v[~eyes], atol=1e-3)


def _similarity_residual(a: torch.Tensor, b: torch.Tensor) -> float:
    """RMS distance of points ``a [N,3]`` to ``b [N,3]`` after the best rotation, scale and shift of a."""
    a0, b0 = a - a.mean(0), b - b.mean(0)
    U, S, Vt = torch.linalg.svd(a0.T @ b0)
    D = torch.diag(torch.tensor([1.0, 1.0, float(torch.sign(torch.det(U @ Vt)))]))
    scale = (S * D.diagonal()).sum() / a0.pow(2).sum()
    return float((scale * a0 @ (U @ D @ Vt) - b0).norm(dim=1).pow(2).mean().sqrt())


def test_identity_is_recovered_up_to_similarity(head, fitted):
    (identity, *_), fit = fitted
    # the face's shape (rotation, scale, position removed; one camera cannot tell them from the pose):
    # measured 0.076 cm from the truth against the ICT neutral's 0.121 cm
    truth = head.landmarks(head.neutral + identity)[:468]
    before = _similarity_residual(head.landmarks(head.neutral)[:468], truth)
    after = _similarity_residual(head.landmarks(fit.neutral)[:468], truth)
    assert after < 0.75 * before, (after, before)


def test_short_clip_needs_an_identity(head, fitted):
    truth = _clip(head, 3)
    lms = _landmarks(head, *truth, outliers=0)
    with pytest.raises(
        MeshsplatError, match=f"too few to fit the head's identity \\(at least {MIN_FRAMES_FOR_IDENTITY}\\)"
    ):
        fit_head(lms, W, H, head=head)
    # with the identity of a longer fit of the same person it fits
    steps = []
    fit = fit_head(
        lms, W, H, identity=fitted[1].identity, head=head, iterations=200, progress=lambda i, n: steps.append((i, n))
    )
    assert float(fit.error_px.max()) < 1.5
    err = (fit.project(head.landmarks(fit.vertices())) - lms[..., :2]).norm(dim=-1)
    assert torch.allclose(err, fit.landmark_error_px, atol=1e-3)
    assert steps[0] == (1, 300) and steps[-1] == (300, 300) and len(steps) == 300


def test_bad_landmarks_are_one_line(head):
    with pytest.raises(MeshsplatError, match=r"landmarks: expected \[T,478,2\|3\]"):
        fit_head(np.zeros((12, 468, 3)), W, H, head=head)
    bad = np.zeros((12, 478, 2))
    bad[[3, 7]] = np.nan
    with pytest.raises(MeshsplatError, match=r"frames \[3, 7\] hold NaN"):
        fit_head(bad, W, H, head=head)
    with pytest.raises(MeshsplatError, match="width: expected a positive integer"):
        fit_head(np.zeros((12, 478, 2)), 0, H, head=head)
    with pytest.raises(MeshsplatError, match="iterations: expected a positive integer"):
        fit_head(np.zeros((12, 478, 2)), W, H, head=head, iterations=0)


def test_a_wrong_focal_length_moves_the_head_not_the_fit(head):
    """A camera of 45 degrees (not the assumed 60): the fit puts the head nearer and still reads
    the expressions and the pose (measured: rotation 2.8 degrees, jaw 0.04 off at most, 0.76 x the distance)."""
    truth = _clip(head, 20)
    f_true = focal_from_fov(W, H, 45.0)
    fit = fit_head(_landmarks(head, *truth, focal=f_true), W, H, head=head)
    assert fit.focal == pytest.approx(focal_from_fov(W, H))
    assert float(fit.landmark_error_px.median(1).values.max()) < 1.5
    assert float(_angle_deg(fit.rotations, truth[3]).max()) < 4.0
    jaw = head.names.index("jawOpen")
    assert float((fit.weights[:, jaw] - truth[1][:, jaw]).abs().max()) < 0.12
    ratio = fit.translations[:, 2] / truth[4][:, 2]
    assert float(ratio.mean()) < 0.9  # nearer: 60 against 45 degrees is a shorter focal length


def test_focal_assumption():
    # 60 degrees across the diagonal: the diagonal's half-length over tan(30 degrees)
    assert focal_from_fov(640, 480) == pytest.approx(400 / math.tan(math.radians(30)))


def test_fit_through_mediapipe_on_renders(head):
    """MediaPipe on photographs of the head (jaw open with the head turned 30 degrees, a smile turned
    the other way, the gaze to the side): the fit reads the pose, the open jaw and the gaze back."""
    mp = pytest.importorskip("mediapipe")

    size = 384
    f = focal_from_fov(size, size)
    K = torch.tensor([[f, 0, size / 2], [0, f, size / 2], [0, 0, 1.0]])
    frames = [  # (weights, yaw degrees, gaze yaw degrees)
        ({}, 0.0, 0.0),
        ({"jawOpen": 0.6}, 30.0, 0.0),
        ({"mouthSmile_L": 0.7, "mouthSmile_R": 0.7}, -20.0, 0.0),
        ({}, 10.0, 18.0),
    ]
    E = len(head.names)
    w = torch.zeros(len(frames), E)
    rot = torch.zeros(len(frames), 3)
    gaze = torch.zeros(len(frames), 2, 2)
    for i, (expr, yaw, gz) in enumerate(frames):
        for name, value in expr.items():
            w[i, head.names.index(name)] = value
        rot[i, 1] = math.radians(yaw)
        gaze[i, :, 0] = math.radians(gz)
    trans = torch.tensor([[0.0, 1.0, -45.0]]).expand(len(frames), 3)
    ident = torch.zeros_like(head.neutral)
    verts = head.pose(ident, w, gaze, rot, trans)
    mesh = mp.solutions.face_mesh.FaceMesh(static_image_mode=True, refine_landmarks=True, max_num_faces=1)
    lms = []
    for v in verts:
        img, _, _ = render_head(head, v, K, size, size)
        res = mesh.process((img.numpy() * 255).round().astype(np.uint8))
        assert res.multi_face_landmarks, "MediaPipe found no face on a render of the ICT head"
        lms.append([(p.x * size, p.y * size, p.z) for p in res.multi_face_landmarks[0].landmark])
    fit = fit_head(np.array(lms), size, size, focal=f, identity=ident, smoothing=0.0, head=head)
    assert float(fit.landmark_error_px.median()) < 2.5, fit.error_px
    assert float(_angle_deg(fit.rotations, rot).max()) < 5.0, _angle_deg(fit.rotations, rot)
    jaw = head.names.index("jawOpen")
    assert float(fit.weights[1, jaw]) > 0.4 and float(fit.weights[0, jaw]) < 0.15, fit.weights[:, jaw]
    smile = [head.names.index("mouthSmile_L"), head.names.index("mouthSmile_R")]
    assert float(fit.weights[2, smile].mean()) > 0.35 and float(fit.weights[0, smile].max()) < 0.2
    # the gaze turned 18 degrees: MediaPipe's iris on these renders reads 6-14 degrees (eyes 0, 1)
    gaze_deg = torch.rad2deg(fit.gaze[..., 0])
    assert float(gaze_deg[3].min()) > 3.0 and float(gaze_deg[3].mean()) > 7.0, gaze_deg
    assert float(gaze_deg[0].abs().max()) < 5.0, gaze_deg
