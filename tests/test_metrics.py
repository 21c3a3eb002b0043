"""The error metrics of pets.evaluate (pure functions): step_errors' parts, the geodesic rotation angles, the
standardized error and obs_std, against independent computations (scipy rotations, hand-computed examples,
the step error as it was first written). The end-to-end check of the JSON keys is in tests/test_offline.py."""

import math

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from envs.catalogue import LAYOUTS
from envs.layout import Group, ObsLayout
from pets.learning.evaluation import (
    HORIZON_KEYS,
    METRICS,
    PARTS,
    entry_differences,
    layout_parts,
    obs_std,
    rotation_angles,
    step_errors,
    wrap_angle,
)

F64 = torch.float64
PI = math.pi


def t(*values):
    return torch.tensor(values, dtype=F64)


def old_total(pred, true, layout):
    """The step error ``total`` as pets.evaluate computed it before the group-aware metrics (verbatim)."""
    dev = pred.device

    def idx(ix):
        return torch.tensor(list(ix), dtype=torch.long, device=dev)

    plain = [i for g in layout.groups if g.kind in ("Rn", "SO2_cossin") for i in g.indices]
    angles = [g.indices[0] for g in layout.groups if g.kind == "SO2_angle"]
    quats = [g.indices for g in layout.groups if g.kind == "SO3_quat"]
    zero = pred.new_zeros(pred.shape[:-1])

    def sq(ix):
        if not ix:
            return zero
        i = idx(ix)
        return (pred.index_select(-1, i) - true.index_select(-1, i)).pow(2).sum(-1)

    position = sq(plain)
    if angles:
        i = idx(angles)
        position = position + wrap_angle(pred.index_select(-1, i) - true.index_select(-1, i)).pow(2).sum(-1)
    if quats:
        i = idx([k for q in quats for k in q])
        q = pred.index_select(-1, i).unflatten(-1, (len(quats), 4))
        q_true = true.index_select(-1, i).unflatten(-1, (len(quats), 4))
        minus, plus = (q - q_true).pow(2).sum(-1), (q + q_true).pow(2).sum(-1)
        position = position + torch.minimum(minus, plus).sum(-1)
    sq_parts = {"position": position, "velocity": sq(layout.velocities), "other": sq(layout.other + layout.derived)}
    return (sq_parts["position"] + sq_parts["velocity"] + sq_parts["other"]).sqrt()


def random_obs(layout, n, gen, scale=1.0):
    """Observations with angles anywhere in (-2 pi, 2 pi), cos/sin pairs and quaternions of any norm and sign."""
    x = torch.randn(n, layout.obs_dim, generator=gen, dtype=F64) * scale
    for g in layout.groups_of("SO2_angle"):
        x[:, g.indices[0]] = (torch.rand(n, generator=gen, dtype=F64) - 0.5) * 4 * PI
    return x


QUAT_LAYOUT = ObsLayout(
    obs_dim=9,
    groups=(Group("pos", "Rn", (0,)), Group("q", "SO3_quat", (1, 2, 3, 4)), Group("hinge", "SO2_angle", (5,))),
    velocities=(6, 7),
    derived=(8,),
)


# --------------------------------------------------------------------------- total: unchanged
@pytest.mark.parametrize("name", [*LAYOUTS, "quat"])
def test_total_is_bit_for_bit_the_old_step_error(name):
    layout = QUAT_LAYOUT if name == "quat" else LAYOUTS[name]()
    gen = torch.Generator().manual_seed(0)
    true = random_obs(layout, 50, gen)
    pred = true + 0.3 * torch.randn(true.shape, generator=gen, dtype=F64)
    pred[::3] = random_obs(layout, len(pred[::3]), gen, 5.0)  # far off, angles across the wrap
    e = step_errors(pred.reshape(5, 10, -1), true.reshape(5, 10, -1), layout, torch.ones(layout.obs_dim))
    assert torch.equal(e["total"], old_total(pred, true, layout).reshape(5, 10))
    assert set(e) == {"total", *PARTS, "standardized"}
    assert all(v.shape == (5, 10) for v in e.values())


# --------------------------------------------------------------------------- rotation
def test_wrap_angle_range_and_values():
    d = t(0.0, 0.5, PI, -PI, 3 * PI, 2 * PI, -0.5 - 4 * PI, 1e-9)
    torch.testing.assert_close(wrap_angle(d), t(0.0, 0.5, PI, PI, PI, 0.0, -0.5, 1e-9), atol=1e-12, rtol=0)
    x = torch.linspace(-20, 20, 4001, dtype=F64)
    w = wrap_angle(x)
    assert (w > -PI).all() and (w <= PI).all()
    torch.testing.assert_close(torch.cos(w), torch.cos(x)), torch.testing.assert_close(torch.sin(w), torch.sin(x))


def quat_obs(rotations, scale=None, sign=None):
    q = rotations.as_quat(scalar_first=True)  # (w, x, y, z) as in MuJoCo; scipy's default is scalar-last
    q = q * (1.0 if scale is None else scale[:, None]) * (1.0 if sign is None else sign[:, None])
    x = np.zeros((len(q), QUAT_LAYOUT.obs_dim))
    x[:, 1:5] = q
    return torch.as_tensor(x)


def test_so3_geodesic_angle_matches_scipy():
    n = 400
    rng = np.random.default_rng(0)
    r_true = Rotation.random(n, random_state=1)
    r_pred = Rotation.random(n, random_state=2)
    # a quarter near-identical (angles 1e-9 .. 1e-3 rad), a quarter near pi
    near = np.arange(n) % 4 == 0
    tiny = rng.normal(size=(n, 3))
    tiny *= (10.0 ** rng.uniform(-9, -3, size=n) / np.linalg.norm(tiny, axis=1))[:, None]
    half = np.arange(n) % 4 == 1
    big = rng.normal(size=(n, 3))
    big *= ((PI - 10.0 ** rng.uniform(-8, -1, size=n)) / np.linalg.norm(big, axis=1))[:, None]
    step = np.where(near[:, None], tiny, big)
    r_pred = Rotation.concatenate(
        [r_true[i] * Rotation.from_rotvec(step[i]) if near[i] or half[i] else r_pred[i] for i in range(n)]
    )

    scale = rng.uniform(0.3, 3.0, size=n)  # predictions off the unit sphere
    sign = np.where(rng.random(n) < 0.5, -1.0, 1.0)  # q and -q are the same rotation
    pred, true = quat_obs(r_pred, scale, sign), quat_obs(r_true, sign=-sign[::-1])
    expected = (r_true.inv() * r_pred).magnitude()  # relative rotation angle in [0, pi]

    angles = rotation_angles(pred, true, QUAT_LAYOUT)
    assert angles.shape == (n, 2)  # the quaternion group and the hinge, in layout order
    np.testing.assert_allclose(angles[:, 0].numpy(), expected, rtol=1e-6, atol=1e-14)
    # relative accuracy at tiny angles, where 2 acos |<q, q'>| has none left
    np.testing.assert_allclose(angles[near, 0].numpy(), expected[near], rtol=1e-5)
    naive = 2 * np.arccos(np.minimum(1, np.abs(np.sum(quat_obs(r_pred).numpy()[:, 1:5] * true.numpy()[:, 1:5], 1))))
    np.testing.assert_allclose(angles[~near, 0].numpy(), naive[~near], atol=1e-7)  # the acos form elsewhere
    assert np.abs(naive[near] - expected[near]).max() > 1e-9  # ... which fails near 0
    e = step_errors(pred, true, QUAT_LAYOUT)
    torch.testing.assert_close(e["rotation"], torch.as_tensor(expected), rtol=1e-6, atol=1e-14)
    torch.testing.assert_close(e["translation"], torch.zeros(n, dtype=F64), rtol=0, atol=0)
    # the paper's error compares unit quaternions up to sign: min |q -+ q'| = sqrt(2 - 2 cos(theta / 2))
    unit = quat_obs(r_pred, sign=sign)
    torch.testing.assert_close(
        step_errors(unit, true, QUAT_LAYOUT)["total"], torch.as_tensor(2 * np.sin(expected / 4)), rtol=0, atol=1e-10
    )
    # the same rotation, any scale and sign: exactly 0 (up to rounding)
    same = rotation_angles(quat_obs(r_true, scale, sign), true, QUAT_LAYOUT)[:, 0]
    assert same.max() < 1e-7


def test_so2_angle_and_cossin_pairs_by_hand():
    layout = ObsLayout(
        obs_dim=5,
        groups=(Group("x", "Rn", (0,)), Group("hinge", "SO2_angle", (1,)), Group("pair", "SO2_cossin", (4, 2))),
        velocities=(3,),
    )

    def obs(angle, pair_angle, pair_norm=1.0):
        return t(0.0, angle, pair_norm * math.sin(pair_angle), 0.0, pair_norm * math.cos(pair_angle))

    cases = [  # (pred, true, hinge angle, pair angle)
        (obs(-PI + 0.05, 0.2), obs(PI - 0.05, 0.2), 0.1, 0.0),  # across +-pi: 0.1, not 2 pi - 0.1
        (obs(0.3 + 4 * PI, -3.0, 2.5), obs(0.3, 3.0), 0.0, 2 * PI - 6.0),  # a non-unit pair, across +-pi
        (obs(1.0 + PI, 0.5 + PI, 0.1), obs(1.0, 0.5), PI, PI),  # half a turn
        (obs(-2.0, 1.0), obs(1.0, -0.25), 3.0, 1.25),
    ]
    pred = torch.stack([c[0] for c in cases])
    true = torch.stack([c[1] for c in cases])
    angles = rotation_angles(pred, true, layout)
    expected = t(*[c[2] for c in cases]), t(*[c[3] for c in cases])
    torch.testing.assert_close(angles, torch.stack(expected, -1), rtol=0, atol=1e-12)
    e = step_errors(pred, true, layout)
    torch.testing.assert_close(e["rotation"], torch.hypot(*expected), rtol=0, atol=1e-12)
    # the paper's error compares the pair as plain numbers: case 1 |(2.5 cos(-3), 2.5 sin(-3)) - (cos 3, sin 3)|
    chord = math.hypot(2.5 * math.cos(-3.0) - math.cos(3.0), 2.5 * math.sin(-3.0) - math.sin(3.0))
    torch.testing.assert_close(e["total"][1], t(chord)[0], rtol=0, atol=1e-12)


def test_no_rotation_groups_give_zero_rotation_error():
    layout = ObsLayout(obs_dim=3, groups=(Group("x", "Rn", (0, 1)),), velocities=(2,))
    pred, true = torch.randn(4, 3, dtype=F64), torch.randn(4, 3, dtype=F64)
    assert rotation_angles(pred, true, layout).shape == (4, 0)
    e = step_errors(pred, true, layout, np.ones(3))
    assert torch.equal(e["rotation"], torch.zeros(4, dtype=F64))
    assert torch.equal(e["other"], torch.zeros(4, dtype=F64)) and torch.equal(e["derived"], torch.zeros(4, dtype=F64))


# --------------------------------------------------------------------------- parts and standardized
HAND_LAYOUT = ObsLayout(
    obs_dim=8,
    groups=(Group("xz", "Rn", (0, 1)), Group("hinge", "SO2_angle", (2,))),
    velocities=(3, 4),
    other=(5,),
    derived=(6, 7),
)


def test_parts_and_standardized_error_by_hand():
    true = t(0, 0, 3.0, 0, 0, 0, 0, 0)
    pred = t(3, 4, -3.0, 1, -2, 0.5, 6, 8)
    std = np.array([1.0, 2.0, 0.5, 0.0, 1.0, 0.25, 7.0, 7.0])  # entry 3 is constant in the training data: 1
    e = step_errors(pred, true, HAND_LAYOUT, std)
    dtheta = 2 * PI - 6.0  # wrap(-3 - 3)
    expected = {
        "translation": 5.0,
        "rotation": dtheta,
        "velocity": math.sqrt(5),
        "other": 0.5,
        "derived": 10.0,
        "total": math.sqrt(25 + dtheta**2 + 5 + 0.25 + 100),
        # the six predicted entries (derived ones excluded) divided by their std: 3, 2, dtheta / 0.5, 1, -2, 2
        "standardized": math.sqrt((9 + 4 + (2 * dtheta) ** 2 + 1 + 4 + 4) / 6),
    }
    assert set(e) == set(expected)
    for key, value in expected.items():
        assert float(e[key]) == pytest.approx(value, rel=1e-12), key
    # the derived entries count in total but not in standardized
    far = pred.clone()
    far[6:] = 1e6
    again = step_errors(far, true, HAND_LAYOUT, std)
    assert float(again["standardized"]) == float(e["standardized"]) and float(again["total"]) > 1e6
    # no obs_std, no standardized error; a wrong shape is refused
    assert "standardized" not in step_errors(pred, true, HAND_LAYOUT)
    with pytest.raises(ValueError, match=r"obs_std must have shape \(8,\)"):
        step_errors(pred, true, HAND_LAYOUT, np.ones(7))
    with pytest.raises(ValueError, match="obs_dim=8"):
        step_errors(pred[:7], true[:7], HAND_LAYOUT)


def test_standardized_quaternions_are_normalised_and_sign_aligned():
    layout = ObsLayout(obs_dim=5, groups=(Group("q", "SO3_quat", (0, 1, 2, 3)), Group("x", "Rn", (4,))))
    a = 0.8  # rotation angle about x
    true = t(1, 0, 0, 0, 0)
    pred = -3.0 * t(math.cos(a / 2), math.sin(a / 2), 0, 0, 0)  # scaled and on the other half of the sphere
    np.testing.assert_allclose(
        entry_differences(pred, true, layout).numpy(), [math.cos(a / 2) - 1, math.sin(a / 2), 0, 0, 0], atol=1e-15
    )
    e = step_errors(pred, true, layout, np.ones(5))
    assert float(e["standardized"]) == pytest.approx(math.sqrt((2 - 2 * math.cos(a / 2)) / 5), rel=1e-12)
    assert float(e["rotation"]) == pytest.approx(a, rel=1e-12)
    same = step_errors(-2.0 * true, true, layout, np.ones(5))  # the same rotation
    assert float(same["standardized"]) == 0 and float(same["rotation"]) == 0


def test_standardized_error_of_an_independent_draw_is_about_sqrt_2():
    gen = torch.Generator().manual_seed(0)
    layout = ObsLayout(obs_dim=4, groups=(Group("x", "Rn", (0, 1)),), velocities=(2, 3))
    scales = t(1e-3, 1.0, 10.0, 1e3)  # units that would let one block dominate a plain Euclidean error
    data = torch.randn(20000, 4, generator=gen, dtype=F64) * scales + t(5, -1, 0, 2)
    true, pred = data[:10000], data[10000:]
    arrays = {"obs": data.numpy()[None], "lengths": np.array([len(data) - 1])}
    e = step_errors(pred, true, layout, obs_std(arrays))
    assert float(e["standardized"].pow(2).mean().sqrt()) == pytest.approx(math.sqrt(2), rel=0.02)
    assert float(step_errors(true, true, layout, obs_std(arrays))["standardized"].max()) == 0


def test_non_finite_predictions_give_non_finite_errors():
    layout = ObsLayout(
        obs_dim=10,
        groups=(Group("x", "Rn", (0,)), Group("pair", "SO2_cossin", (1, 2)), Group("q", "SO3_quat", (3, 4, 5, 6))),
        velocities=(7,),
        other=(8,),
        derived=(9,),
    )
    true = t(0, 1, 0, 1, 0, 0, 0, 0, 0, 0).expand(6, 10).clone()
    pred = true.clone()
    inf, nan = float("inf"), float("nan")
    pred[0, 0] = inf
    pred[1, 2] = inf  # atan2(inf, 1) would be a finite pi / 2
    pred[2, 4] = inf
    pred[3, 3:7] = nan
    pred[4, 7] = -inf
    pred[5, 8] = nan
    e = step_errors(pred, true, layout, np.ones(10))
    for key in ("total", "standardized"):
        assert not torch.isfinite(e[key]).any(), key
    part = {0: "translation", 1: "rotation", 2: "rotation", 3: "rotation", 4: "velocity", 5: "other"}
    for row, name in part.items():
        assert not math.isfinite(e[name][row]), (row, name)
        assert all(math.isfinite(e[other][row]) for other in PARTS if other != name), row


def test_entry_differences_wrap_angles_and_keep_the_rest_plain():
    d = entry_differences(t(0.5, 1.0, -PI + 0.1, 2, 3, 4, 5, 6), t(0.25, -1.0, PI - 0.1, 0, 0, 0, 0, 0), HAND_LAYOUT)
    torch.testing.assert_close(d, t(0.25, 2.0, 0.2, 2, 3, 4, 5, 6), rtol=0, atol=1e-12)


# --------------------------------------------------------------------------- layouts and obs_std
@pytest.mark.parametrize("name", list(LAYOUTS))
def test_catalogue_layouts_split_into_parts_and_each_entry_moves_only_its_part(name):
    layout = LAYOUTS[name]()
    parts = layout_parts(layout)
    assert set(parts) == set(PARTS)
    assert sorted(i for ix in parts.values() for i in ix) == list(range(layout.obs_dim))
    gen = torch.Generator().manual_seed(1)
    true = random_obs(layout, 1, gen)[0]
    for g in layout.groups_of("SO3_quat"):
        true[list(g.indices)] /= true[list(g.indices)].norm()
    part_of = {i: p for p, ix in parts.items() for i in ix}
    n = layout.obs_dim
    pred = true.expand(n, n) + 0.1 * torch.eye(n, dtype=F64)  # row i moves entry i only
    e = step_errors(pred, true.expand(n, n), layout, np.ones(n))
    for i in range(n):
        moved = {p for p in PARTS if float(e[p][i]) > 1e-12}
        assert moved == {part_of[i]}, (i, moved)
        assert (float(e["standardized"][i]) > 0) == (i not in layout.derived), i


def test_known_parts_of_ant_and_reacher():
    ant, reacher = layout_parts(LAYOUTS["ant"]()), layout_parts(LAYOUTS["reacher"]())
    assert ant["translation"] == (0, 1, 2, 107) and ant["rotation"] == tuple(range(3, 15))
    assert ant["velocity"] == tuple(range(15, 29)) and ant["derived"] == tuple(range(29, 107)) and ant["other"] == ()
    assert reacher["rotation"] == (0, 2, 1, 3) and reacher["translation"] == (4, 5)
    assert reacher["velocity"] == (6, 7) and reacher["other"] == (8, 9) and reacher["derived"] == ()


def test_obs_std_uses_only_the_real_observations():
    nan = float("nan")
    obs = np.array(
        [
            [[0.0, 1.0], [2.0, 1.0], [4.0, 1.0], [6.0, 1.0]],  # 3 steps: 4 real observations
            [[1.0, 1.0], [3.0, 1.0], [nan, nan], [nan, nan]],  # 1 step: 2 real, then padding
        ]
    )
    std = obs_std({"obs": obs, "lengths": np.array([3, 1])})
    np.testing.assert_allclose(std, [np.std([0, 2, 4, 6, 1, 3]), 0.0])


def test_metric_names():
    assert METRICS == (
        "mean_step_error",
        "final_step_error",
        "translation_error",
        "rotation_error",
        "velocity_error",
        "other_error",
        "derived_error",
        "standardized_error",
    )
    assert HORIZON_KEYS == (*METRICS, "nonfinite_fraction")


def test_each_codec_owns_its_step_terms_and_the_quaternion_term_is_the_chordal_distance_of_scipys_rotations():
    """The step error's terms come from the codecs; for unit quaternions the SO3_quat term
    min(|q - q'|^2, |q + q'|^2) is 2 - 2 |<q, q'>| (the same rotation: 0, whichever sign scipy gives q)."""
    from scipy.spatial.transform import Rotation

    from gem_head.codecs import CODECS

    r, r2 = Rotation.random(200, random_state=1), Rotation.random(200, random_state=2)
    q = torch.tensor(r.as_quat(scalar_first=True))
    q2 = torch.tensor(r2.as_quat(scalar_first=True))
    term = CODECS["SO3_quat"].step_terms(q, q2)
    assert term.shape == (200, 1)
    torch.testing.assert_close(term[:, 0], 2 - 2 * (q * q2).sum(-1).abs())
    assert torch.allclose(CODECS["SO3_quat"].step_terms(q, -q), torch.zeros(200, 1, dtype=F64))
    a = t(0.1, 3.0, -3.0)
    torch.testing.assert_close(CODECS["SO2_angle"].step_terms(a, -a), wrap_angle(2 * a).pow(2))
    assert [CODECS[k].step_place for k in ("Rn", "SO2_cossin", "SO2_angle", "SO3_quat")] == [0, 0, 1, 2]
