"""The GEM head's group codecs (gem_head.codecs): one codec class per kind, looped over by GemHead / GemSEHead.

A new kind is one codec class and one registry entry: a toy kind (hinge angles observed in degrees) is registered
from this file and checked against the built-in ``SO2_angle`` codec on real HalfCheetah transitions. Every codec
is gradchecked in float64 through encode -> decode on real transitions.
"""

from __future__ import annotations

import math
from collections.abc import Iterator

import pytest
import torch

import envs
from envs.layout import KIND_WIDTH, Group, ObsLayout
from gem_head.codecs import CODECS, GroupCodec, SO2Codec, put, register_codec, sel, take, unregister_codec
from gem_head.head import GemHead
from gem_head.lie import wrap_angle
from gem_head.se_root import GemSEHead
from pets.data.rollout import collect_random

DEG = 180.0 / math.pi


class SO2DegreesCodec(SO2Codec):
    """A hinge angle observed in degrees d: theta = d pi / 180, target alpha = wrap(theta' - theta) (radians),
    decoding d' = d + alpha 180 / pi; inputs (cos theta, sin theta); Frobenius term from SO2Codec."""

    kind, width = "SO2_deg", 1

    def __init__(self, obs: list[int], slots: list[int], layout: ObsLayout, compose: str) -> None:
        super().__init__(obs, slots, layout, compose)
        self.deg = sel(self.obs)

    def radians(self, obs: torch.Tensor) -> torch.Tensor:
        return take(obs, self.deg) / DEG

    def input_names(self) -> list[str]:
        return [f"cos obs[{i}] (deg)" for i in self.obs] + [f"sin obs[{i}] (deg)" for i in self.obs]

    def inputs(self, obs: torch.Tensor) -> list[torch.Tensor]:
        return list(self.cos_sin(obs))

    def target(self, obs: torch.Tensor, next_obs: torch.Tensor, out: torch.Tensor) -> None:
        put(out, self.tgt, wrap_angle(self.radians(next_obs) - self.radians(obs)))

    def decode(self, obs: torch.Tensor, target: torch.Tensor, out: torch.Tensor) -> None:
        put(out, self.deg, take(obs, self.deg) + take(target, self.tgt) * DEG)

    def cos_sin(self, obs: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        theta = self.radians(obs)
        return torch.cos(theta), torch.sin(theta)


@pytest.fixture
def degrees_kind() -> Iterator[str]:
    register_codec(SO2DegreesCodec)
    yield SO2DegreesCodec.kind
    unregister_codec(SO2DegreesCodec.kind)


def transitions(env: str, n: int) -> tuple[envs.EnvSpec, torch.Tensor, torch.Tensor, torch.Tensor]:
    spec = envs.get(env)
    obs, act, nxt = (torch.as_tensor(x, dtype=torch.float64) for x in collect_random(spec, n, 0))
    return spec, obs, act, nxt


def in_degrees(layout: ObsLayout) -> tuple[ObsLayout, list[int]]:
    """``layout`` with every SO2_angle group of kind SO2_deg (no root), and the indices that changed."""
    groups = tuple(Group(g.name, "SO2_deg", g.indices) if g.kind == "SO2_angle" else g for g in layout.groups)
    fields = {k: getattr(layout, k) for k in ("obs_dim", "velocities", "other", "invariant", "derived")}
    return ObsLayout(groups=groups, **fields), [i for g in layout.groups_of("SO2_angle") for i in g.indices]


def test_a_kind_registered_from_outside_is_one_codec_and_one_entry(degrees_kind: str) -> None:
    """The toy kind builds a head whose targets, inputs, losses and decoding are the SO2_angle head's, in degrees."""
    spec, obs, act, nxt = transitions("halfcheetah", 200)
    layout, angles = in_degrees(spec.layout)
    gem, deg = GemHead(spec.layout, spec.act_dim), GemHead(layout, spec.act_dim)
    assert [type(c) for c in deg.codecs] == [CODECS["Rn"], SO2DegreesCodec]
    assert deg.target_names == gem.target_names and deg.group_slots == gem.group_slots

    def to_deg(x: torch.Tensor) -> torch.Tensor:
        out = x.clone()
        out[:, angles] = x[:, angles] * DEG
        return out

    o_deg, n_deg = to_deg(obs), to_deg(nxt)
    y = gem.targets(obs, nxt)
    torch.testing.assert_close(deg.targets(o_deg, n_deg), y, rtol=0, atol=1e-12)
    torch.testing.assert_close(deg.inputs(o_deg, act), gem.inputs(obs, act), rtol=0, atol=1e-12)
    noisy = y + 0.2 * torch.randn(y.shape, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    torch.testing.assert_close(deg.next_obs(o_deg, noisy), to_deg(gem.next_obs(obs, noisy)), rtol=0, atol=1e-9)
    torch.testing.assert_close(deg.next_obs(o_deg, deg.targets(o_deg, n_deg)), n_deg, rtol=0, atol=1e-9)
    e = [x.reshape(2, 100, -1) for x in (noisy, y, obs, nxt, o_deg, n_deg)]
    torch.testing.assert_close(
        deg.frobenius_loss(e[0], e[1], e[4], e[5]), gem.frobenius_loss(*e[:4]), rtol=1e-12, atol=0
    )


def test_registering_a_kind_makes_layouts_accept_it_and_unregistering_removes_it() -> None:
    with pytest.raises(ValueError, match="unknown kind") as info:
        Group("hinge", "SO2_deg", (0,))
    assert "module that calls gem_head.codecs.register_codec is imported" in str(info.value)  # what to do
    assert "imports=[my_codec]" in str(info.value) and "\n" not in str(info.value)
    register_codec(SO2DegreesCodec)
    try:
        assert KIND_WIDTH["SO2_deg"] == 1 and Group("hinge", "SO2_deg", (0,)).kind == "SO2_deg"
        with pytest.raises(ValueError, match="already registered"):
            register_codec(type("Other", (SO2DegreesCodec,), {}))
    finally:
        unregister_codec("SO2_deg")
    assert "SO2_deg" not in CODECS and "SO2_deg" not in KIND_WIDTH
    with pytest.raises(ValueError, match="unknown kind"):
        Group("hinge", "SO2_deg", (0,))


@pytest.mark.parametrize(
    "env,model,kinds",
    [
        ("halfcheetah", GemHead, ["Rn", "SO2_angle"]),
        ("reacher", GemHead, ["Rn", "SO2_cossin"]),
        ("ant", GemHead, ["Rn", "SO2_angle", "SO3_quat"]),
        ("ant", GemSEHead, ["Rn", "SO2_angle", "SO3_quat", "SE3"]),
        ("hopper", GemSEHead, ["Rn", "SO2_angle", "SE2"]),
    ],
)
def test_the_head_is_its_codecs(env: str, model: type[GemHead], kinds: list[str]) -> None:
    """One codec per kind present (the root codec last); the inputs are the codecs' features then the action; every
    target slot belongs to exactly one group codec."""
    spec = envs.get(env)
    head = model(spec.layout, spec.act_dim)
    assert [c.kind for c in head.codecs] == kinds
    names = [n for c in head.codecs for n in c.input_names()] + [f"act[{j}]" for j in range(spec.act_dim)]
    assert list(head.input_names) == names
    slots = sorted(s for c in head.codecs if not getattr(c, "composite", False) for s in c.slots)
    assert slots == list(range(head.target_dim))


def encode(head: GemHead, obs: torch.Tensor, nxt: torch.Tensor) -> torch.Tensor:
    """head.targets as the codecs define it, differentiably (the head's additive step writes with ``out=``)."""
    out = obs.new_zeros(len(obs), head.target_dim)
    for c in head.codecs:
        if c.additive:
            out[:, c.slots] = nxt[:, c.obs] - obs[:, c.obs]
    for c in head.codecs:
        c.target(obs, nxt, out)
    return out


def decode(head: GemHead, obs: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """head.next_obs as the codecs define it, differentiably."""
    out = obs.clone()
    for c in head.codecs:
        if c.additive:
            out[:, c.obs] = obs[:, c.obs] + target[:, c.slots]
    for c in head.codecs:
        c.decode(obs, target, out)
    return out


def _codec_map(head: GemHead, codec: GroupCodec):
    """(obs, next_obs, noise) -> the codec's inputs, target slots, decoded entries and Frobenius term."""

    def f(obs: torch.Tensor, nxt: torch.Tensor, noise: torch.Tensor) -> torch.Tensor:
        y = encode(head, obs, nxt)
        feats = [x.flatten(1) for x in codec.inputs(obs)]
        dec = decode(head, obs, y + noise)[:, codec.obs]
        frob = codec.frobenius(y + noise, y, obs, nxt, None)
        extra = [] if frob is None else [frob.reshape(len(obs), -1)]
        return torch.cat([*feats, y[:, codec.slots], dec, *extra], dim=1)

    return f


CASES = [
    ("halfcheetah", GemHead, "Rn", "right"),
    ("halfcheetah", GemHead, "SO2_angle", "right"),
    ("reacher", GemHead, "SO2_cossin", "right"),
    ("ant", GemHead, "SO3_quat", "right"),
    ("ant", GemHead, "SO3_quat", "left"),
    ("hopper", GemSEHead, "SE2", "right"),
    ("ant", GemSEHead, "SE3", "right"),
    ("halfcheetah", GemHead, "SO2_deg", "right"),
]


@pytest.mark.parametrize("env,model,kind,compose", CASES)
def test_gradcheck_encode_decode_of_every_codec(env: str, model: type[GemHead], kind: str, compose: str) -> None:
    """float64 gradcheck of each codec's inputs, targets, decoding and Frobenius term on real transitions."""
    spec, obs, _, nxt = transitions(env, 40)
    layout = spec.layout
    if kind == "SO2_deg":
        register_codec(SO2DegreesCodec)
        layout = in_degrees(layout)[0]
    try:
        head = model(layout, spec.act_dim, compose=compose)
        (codec,) = [c for c in head.codecs if c.kind == kind]
        rows = [0, 17, 33]
        noise = 0.1 * torch.randn(3, head.target_dim, generator=torch.Generator().manual_seed(1), dtype=torch.float64)
        o, n = obs[rows], nxt[rows]
        torch.testing.assert_close(encode(head, o, n), head.targets(o, n), rtol=0, atol=0)
        torch.testing.assert_close(decode(head, o, noise), head.next_obs(o, noise), rtol=0, atol=0)
        args = tuple(x.clone().requires_grad_(True) for x in (o, n, noise))
        assert torch.autograd.gradcheck(_codec_map(head, codec), args)
    finally:
        if kind == "SO2_deg":
            unregister_codec(kind)


@pytest.mark.parametrize(
    ("attrs", "message"),
    [
        ({"width": 1, "tangent_dim": 1}, "set the class attribute kind"),
        ({"kind": "K", "tangent_dim": 1}, "width must be"),
        ({"kind": "K", "width": 0, "tangent_dim": 1}, "width must be"),
        ({"kind": "K", "width": 1, "tangent_dim": 0}, "tangent_dim must be"),
        ({"kind": "K", "width": 1, "tangent_dim": 1}, "must define target and decode"),
        ({"kind": "K", "width": 1, "tangent_dim": 1, "target": SO2DegreesCodec.target}, "must define decode"),
        ({"kind": "K", "width": 1, "tangent_dim": 1, "additive": True, "is_rotation": True},
         "must define rotation_angle"),
    ],
)  # fmt: skip
def test_an_incomplete_codec_is_refused_at_registration_in_one_line(attrs: dict, message: str) -> None:
    """A codec without its attributes, or a non-additive one without its maps (the base class's write nothing: a head
    built on it would return whatever memory its outputs were allocated in), or a rotation without its evaluation's
    rotation_angle (pets.evaluate would raise NotImplementedError), is refused before any layout takes it."""
    with pytest.raises(ValueError, match=message) as info:
        register_codec(type("Incomplete", (GroupCodec,), attrs))
    assert "\n" not in str(info.value) and "K" not in CODECS and "K" not in KIND_WIDTH
    with pytest.raises(TypeError, match="subclass of gem_head.codecs.GroupCodec"):
        register_codec(SO2DegreesCodec.target)


def test_an_additive_codec_may_keep_the_base_maps() -> None:
    """An additive kind's entries already hold next - obs and obs + target: the base maps' nothing is right."""
    cls = type("Plain", (GroupCodec,), {"kind": "Plain1", "width": 1, "tangent_dim": 1, "additive": True})
    try:
        assert register_codec(cls) is cls and CODECS["Plain1"] is cls
    finally:
        unregister_codec("Plain1")
