"""A user's own group codec for the tests and docs/models.md, registered when the module is imported: name it in the
config key ``imports`` (``imports=[tests.own_codec]``; from your folder, ``imports=[own_codec]``).

Kind ``SO2_wrapped``: a hinge angle theta in radians, as ``SO2_angle``, whose decoded next angle is wrapped to
(-pi, pi] (``SO2_angle`` never wraps: MuJoCo's hinge positions are unbounded). Inputs (cos theta, sin theta);
target alpha = wrap(theta' - theta); decoding theta' = wrap(theta + alpha). A rotation: the evaluation scores it by
``rotation_angle``. An env uses it through its layout, ``Group("hinge", "SO2_wrapped", (1,))``, built once the
module is imported.
"""

from __future__ import annotations

import torch
from torch import Tensor

from gem_head.codecs import SO2Codec, put, register_codec, sel, take
from gem_head.lie import wrap_angle


@register_codec
class SO2WrappedCodec(SO2Codec):
    """SO(2) from a hinge angle, decoded into (-pi, pi]; the Frobenius term is SO2Codec's (from ``cos_sin``)."""

    kind, width, is_rotation = "SO2_wrapped", 1, True

    @classmethod
    def rotation_angle(cls, pred: Tensor, true: Tensor) -> Tensor:
        return wrap_angle(pred[..., 0] - true[..., 0]).abs()

    def __init__(self, obs: list[int], slots: list[int], layout, compose: str) -> None:
        super().__init__(obs, slots, layout, compose)
        self.ang = sel(self.obs)

    def input_names(self) -> list[str]:
        return [f"cos obs[{i}]" for i in self.obs] + [f"sin obs[{i}]" for i in self.obs]

    def inputs(self, obs: Tensor) -> list[Tensor]:
        return list(self.cos_sin(obs))

    def target(self, obs: Tensor, next_obs: Tensor, out: Tensor) -> None:
        put(out, self.tgt, wrap_angle(take(next_obs, self.ang) - take(obs, self.ang)))

    def decode(self, obs: Tensor, target: Tensor, out: Tensor) -> None:
        put(out, self.ang, wrap_angle(take(obs, self.ang) + take(target, self.tgt)))

    def cos_sin(self, obs: Tensor) -> tuple[Tensor, Tensor]:
        theta = take(obs, self.ang)
        return torch.cos(theta), torch.sin(theta)
