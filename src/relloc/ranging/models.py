"""Range-error models (PyTorch): stacked LSTM, bidirectional LSTM and ConvLSTM.

The derivation: docs/explanation/internals.md, section ``relloc.ranging.models``.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import asdict, dataclass
from typing import Any

import torch
from torch import nn

VARIANTS: tuple[str, ...] = ("stacked", "bilstm", "convlstm")


def _paper_features(w: torch.Tensor) -> torch.Tensor:
    """The paper's inputs as they are: ``[range, yaw_a, yaw_b]``."""
    return w


def _window_relative_range(r: torch.Tensor) -> torch.Tensor:
    """Range minus the window's mean range: the recent trajectory's shape, not its level."""
    return r - r.mean(dim=-1, keepdim=True)


def _relative_features(w: torch.Tensor) -> torch.Tensor:
    """Default inputs: ``[range - window mean, sin yaw_a, cos yaw_a, sin yaw_b, cos yaw_b]``.

    No absolute range: in a recording where robots drive fixed patterns, their headings encode
    where they are, so a model given both the absolute range and the headings learns
    ``error = range - distance(headings)`` for that one geometry, which scores very well on
    the same session and fails on the next (see docs/explanation/range-correction.md). The range relative to the
    window keeps what transfers: spikes (NLOS) and lag while the distance changes. Yaws enter
    as sine and cosine: no jump at +-pi, and the antenna pattern is periodic.
    """
    r, ya, yb = w[..., 0], w[..., 1], w[..., 2]
    return torch.stack(
        [_window_relative_range(r), torch.sin(ya), torch.cos(ya), torch.sin(yb), torch.cos(yb)],
        dim=-1,
    )


def _invariant_features(w: torch.Tensor) -> torch.Tensor:
    """Heading-frame-free inputs: ``[range - window mean, sin(yaw_a - yaw_b), cos(...)]``.

    Unchanged by a rotation of the shared heading frame: for deployments whose headings are
    not in the frame the training data used (the motion-capture frame for the TIERS data).
    """
    r, ya, yb = w[..., 0], w[..., 1], w[..., 2]
    return torch.stack([_window_relative_range(r), torch.sin(ya - yb), torch.cos(ya - yb)], dim=-1)


FEATURE_SETS: dict[str, tuple[int, Callable[[torch.Tensor], torch.Tensor]]] = {
    "relative": (5, _relative_features),
    "invariant": (3, _invariant_features),
    "paper": (3, _paper_features),
}
"""Name -> (features per frame, function of a raw ``(B, T, 3)`` window)."""


@dataclass(frozen=True)
class Architecture:
    """Shape of a range-error model. Defaults follow the paper."""

    variant: str = "stacked"
    """``stacked`` (LSTM layers), ``bilstm`` (bidirectional LSTM layers) or ``convlstm``."""
    hidden: tuple[int, ...] = (50, 50)
    """Units (LSTM) or filters (ConvLSTM) of each recurrent layer."""
    dropout: float = 0.3
    """Dropout after each recurrent layer (training only)."""
    features: str = "relative"
    """Input feature set, a key of :data:`FEATURE_SETS`."""
    conv_subseq: int = 5
    """ConvLSTM: frames per sub-sequence (the convolved axis); must divide ``n_steps``."""
    conv_kernel: int = 3
    """ConvLSTM: odd kernel size of the convolutions along a sub-sequence."""

    def __post_init__(self) -> None:
        if self.variant not in VARIANTS:
            raise ValueError(f"variant must be one of {VARIANTS}, got {self.variant!r}")
        if not self.hidden or any(h < 1 for h in self.hidden):
            raise ValueError(f"hidden must be positive layer sizes, got {self.hidden}")
        if not 0.0 <= self.dropout < 1.0:
            raise ValueError(f"dropout must be in [0, 1), got {self.dropout}")
        if self.features not in FEATURE_SETS:
            raise ValueError(
                f"features must be one of {sorted(FEATURE_SETS)}, got {self.features!r}"
            )
        if self.conv_kernel < 1 or self.conv_kernel % 2 == 0:
            raise ValueError(f"conv_kernel must be odd, got {self.conv_kernel}")

    @property
    def n_features(self) -> int:
        return FEATURE_SETS[self.features][0]

    def to_dict(self) -> dict[str, Any]:
        d = asdict(self)
        d["hidden"] = list(self.hidden)
        return d

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> Architecture:
        d = dict(d)
        d["hidden"] = tuple(int(h) for h in d["hidden"])
        return cls(**d)


@dataclass(frozen=True)
class Normalisation:
    """Feature and target statistics of the training windows (stored in the model)."""

    feature_mean: tuple[float, ...]
    feature_std: tuple[float, ...]
    target_mean: float = 0.0
    target_std: float = 1.0


class FeatureTransform(nn.Module):
    """Raw ``(B, T, 3)`` window -> z-normalised ``(B, T, F)`` features.

    A feature that was constant in training (e.g. the yaw of a robot that never turned) has
    standard deviation 0: the model cannot have learnt anything about it, so it is masked to 0
    rather than divided by a tiny number, which would turn a different value at run time (the
    robot parked facing elsewhere) into a huge input.
    """

    mean: torch.Tensor
    scale: torch.Tensor

    def __init__(self, features: str, n_features: int) -> None:
        super().__init__()
        self.features = features
        self.register_buffer("mean", torch.zeros(n_features))
        self.register_buffer("scale", torch.ones(n_features))

    def raw(self, window: torch.Tensor) -> torch.Tensor:
        """Features before normalisation (used to compute the statistics)."""
        return FEATURE_SETS[self.features][1](window)

    def set_statistics(self, mean: torch.Tensor, std: torch.Tensor) -> None:
        """``scale = 1/std``, or 0 where the feature did not vary (std < 1e-6)."""
        with torch.no_grad():
            self.mean.copy_(mean)
            varies = std > 1e-6
            self.scale.copy_(torch.where(varies, 1.0 / torch.where(varies, std, 1.0), 0.0))

    def forward(self, window: torch.Tensor) -> torch.Tensor:
        return (self.raw(window) - self.mean) * self.scale


class ConvLSTMCell1d(nn.Module):
    """ConvLSTM cell over a 1-D spatial axis: LSTM gates computed by convolutions.

    ``x``: ``(B, C_in, L)``; state ``h, c``: ``(B, C_hidden, L)``. Gates
    ``i, f, g, o = conv_x(x) + conv_h(h)`` then ``c' = s(f) c + s(i) tanh(g)``,
    ``h' = s(o) tanh(c')``. The first step takes no state (zeros): it avoids building a zero
    tensor whose batch size the ONNX exporter would freeze.
    """

    def __init__(self, in_channels: int, hidden: int, kernel: int) -> None:
        super().__init__()
        self.hidden = hidden
        self.conv_x = nn.Conv1d(in_channels, 4 * hidden, kernel, padding=kernel // 2)
        self.conv_h = nn.Conv1d(hidden, 4 * hidden, kernel, padding=kernel // 2, bias=False)
        bias = self.conv_x.bias
        assert bias is not None  # Conv1d's default bias=True
        with torch.no_grad():  # forget-gate bias 1: remember by default, as Keras does
            bias[hidden : 2 * hidden].fill_(1.0)

    def forward(
        self, x: torch.Tensor, state: tuple[torch.Tensor, torch.Tensor] | None
    ) -> tuple[torch.Tensor, torch.Tensor]:
        gates = self.conv_x(x)
        if state is not None:
            gates = gates + self.conv_h(state[0])
        i, f, g, o = gates.chunk(4, dim=1)
        c = torch.sigmoid(i) * torch.tanh(g)
        if state is not None:
            c = c + torch.sigmoid(f) * state[1]
        h = torch.sigmoid(o) * torch.tanh(c)
        return h, c


class ConvLSTM1d(nn.Module):
    """One ConvLSTM layer: steps a :class:`ConvLSTMCell1d` through ``(B, S, C, L)`` input."""

    def __init__(self, in_channels: int, hidden: int, kernel: int) -> None:
        super().__init__()
        self.cell = ConvLSTMCell1d(in_channels, hidden, kernel)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """Returns the hidden states of every step, ``(B, S, C_hidden, L)``."""
        state: tuple[torch.Tensor, torch.Tensor] | None = None
        outputs = []
        for s in range(x.shape[1]):
            state = self.cell(x[:, s], state)
            outputs.append(state[0])
        return torch.stack(outputs, dim=1)


class RangeErrorModel(nn.Module):
    """Raw window ``(B, n_steps, 3)`` -> predicted residual and its sigma, ``(B, 1)`` each, m."""

    target_mean: torch.Tensor
    target_std: torch.Tensor
    sigma_scale: torch.Tensor

    def __init__(self, arch: Architecture, n_steps: int) -> None:
        super().__init__()
        if arch.variant == "convlstm" and n_steps % arch.conv_subseq != 0:
            raise ValueError(
                f"convlstm needs n_steps ({n_steps}) divisible by conv_subseq ({arch.conv_subseq})"
            )
        self.arch = arch
        self.n_steps = n_steps
        self.transform = FeatureTransform(arch.features, arch.n_features)
        self.dropout = nn.Dropout(arch.dropout)
        self.register_buffer("target_mean", torch.zeros(()))
        self.register_buffer("target_std", torch.ones(()))
        self.register_buffer("sigma_scale", torch.ones(()))
        layers: list[nn.Module] = []
        size = arch.n_features
        if arch.variant in ("stacked", "bilstm"):
            bidirectional = arch.variant == "bilstm"
            for h in arch.hidden:
                layers.append(nn.LSTM(size, h, batch_first=True, bidirectional=bidirectional))
                size = h * (2 if bidirectional else 1)
            out_size = size
        else:
            for h in arch.hidden:
                layers.append(ConvLSTM1d(size, h, arch.conv_kernel))
                size = h
            out_size = size * arch.conv_subseq
        self.recurrent = nn.ModuleList(layers)
        self.head = nn.Linear(out_size, 1)
        self.sigma_head = nn.Linear(out_size, 1)

    def set_normalisation(self, norm: Normalisation) -> None:
        """Store training statistics in the model's buffers."""
        self.transform.set_statistics(
            torch.tensor(norm.feature_mean, dtype=torch.float32),
            torch.tensor(norm.feature_std, dtype=torch.float32),
        )
        with torch.no_grad():
            self.target_mean.fill_(norm.target_mean)
            self.target_std.fill_(norm.target_std)

    def forward_normalised(self, window: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Predicted target and its standard deviation in training units, each ``(B, 1)``.

        The standard deviation comes from the detached recurrent features (``softplus`` plus a
        floor of 1e-3): its loss trains only :attr:`sigma_head`, never the error prediction.
        """
        x = self.transform(window)
        if self.arch.variant == "convlstm":
            b, t, f = x.shape
            sub = self.arch.conv_subseq
            # (B, T, F) -> (B, S, L, F) -> (B, S, F, L): channels are features, L is convolved.
            x = x.reshape(b, t // sub, sub, f).transpose(2, 3)
            for layer in self.recurrent:
                x = self.dropout(layer(x))
            last = x[:, -1].flatten(1)
        else:
            for layer in self.recurrent:
                x, _ = layer(x)
                x = self.dropout(x)
            if self.arch.variant == "bilstm":
                # Forward direction after the newest frame, backward direction after the
                # oldest: each has then read the whole window (Keras' Bidirectional(LSTM)).
                h = self.arch.hidden[-1]
                last = torch.cat([x[:, -1, :h], x[:, 0, h:]], dim=1)
            else:
                last = x[:, -1]
        sigma = nn.functional.softplus(self.sigma_head(last.detach())) + 1e-3
        return self.head(last), sigma

    def forward(self, window: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """``(residual, sigma)`` in metres, each ``(B, 1)``: the predicted error around the
        pair's constant and the standard deviation of what remains after subtracting it."""
        mu, sigma = self.forward_normalised(window)
        return (
            mu * self.target_std + self.target_mean,
            sigma * self.target_std * self.sigma_scale,
        )


class EnsembleModel(nn.Module):
    """Members trained alone from different seeds, in one graph: window -> (residual, sigma).

    ``residual`` is the members' mean; ``sigma^2`` is the mean of their own variances plus the
    variance of their residuals around that mean (the law of total variance over members), so
    the sigma grows where the members disagree: on inputs unlike the training data, which is
    what a new session brings. :attr:`sigma_scale` calibrates it on the validation blocks. One
    member is a plain model (its spread is zero).
    """

    sigma_scale: torch.Tensor

    def __init__(self, members: list[RangeErrorModel]) -> None:
        super().__init__()
        if not members:
            raise ValueError("an ensemble needs at least one member")
        self.arch = members[0].arch
        self.n_steps = members[0].n_steps
        if any(m.arch != self.arch or m.n_steps != self.n_steps for m in members):
            raise ValueError("ensemble members must share architecture and n_steps")
        self.members = nn.ModuleList(members)
        self.register_buffer("sigma_scale", torch.ones(()))

    def forward(self, window: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        outputs = [m(window) for m in self.members]
        mus = torch.stack([o[0] for o in outputs])  # (K, B, 1)
        variances = torch.stack([o[1] ** 2 for o in outputs])
        mu = mus.mean(dim=0)
        var = variances.mean(dim=0) + ((mus - mu) ** 2).mean(dim=0)
        return mu, torch.sqrt(var) * self.sigma_scale


def build_model(arch: Architecture, n_steps: int) -> RangeErrorModel:
    """A fresh model (call :meth:`RangeErrorModel.set_normalisation` before training)."""
    return RangeErrorModel(arch, n_steps)
