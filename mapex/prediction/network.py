"""A LaMa-style inpainting generator sized for CPU inference (docs/prediction.md).

Fast Fourier convolutions (FFC) let every block see the whole map. The trunk works at
1/`downscale` resolution: the observed map is folded into channels (pixel unshuffle), passes
a stem convolution and `n_blocks` FFC residual blocks and is unfolded back (pixel shuffle)
to one logit per cell; a small full-resolution refinement then aligns those logits with the
observed walls. Any map size is accepted (padded to a multiple of `downscale`, cropped
back); cells beyond the map's border encode as all zeros; weights and activations are kept
channels-last (NHWC). Why each of these: docs/prediction.md.
"""

from __future__ import annotations

import numpy as np
import torch
from torch import nn
from torch.nn import functional as F

from mapex.grid import FREE, OCCUPIED, UNKNOWN
from mapex.prediction.config import NetworkConfig, Precision

INPUT_CHANNELS = 3  # free, occupied, unknown (one-hot of the observed codes)
OUTSIDE_MAP = np.uint8(255)  # not a map code: a cell beyond the map's border (all-zero encoding)
CODE_CHANNELS = (int(FREE), int(OCCUPIED), int(UNKNOWN))  # the code of each input channel


def encode_observed(observed: np.ndarray) -> np.ndarray:
    """Observed codes (rows, cols) -> float32 one-hot (3, rows, cols): free, occupied, unknown.

    Any other value (`OUTSIDE_MAP`) encodes as all zeros: beyond the map's border."""
    return np.stack([observed == code for code in CODE_CHANNELS]).astype(np.float32)


def autocast(device: torch.device, precision: Precision) -> torch.autocast:
    """The context in which a forward pass on `device` runs at `precision`: under bfloat16
    autocast, or plain float32."""
    return torch.autocast(device.type, dtype=torch.bfloat16, enabled=precision == "bfloat16")


def emulated_bfloat16(device: torch.device, precision: Precision) -> bool:
    """Whether `precision` asks for bfloat16 on a CPU without native bfloat16 (no AVX512-BF16
    or AMX), where oneDNN emulates it: a training step there is about ten times slower than
    in float32 (measured on a 2-core AVX2 EPYC: 5.6 s against 0.5 s)."""
    return (
        precision == "bfloat16"
        and device.type == "cpu"
        and not torch.ops.mkldnn._is_mkldnn_bf16_supported()
    )


class FourierUnit(nn.Module):
    """1x1 convolution in the 2-D frequency domain (real and imaginary parts as channels)."""

    def __init__(self, channels: int) -> None:
        super().__init__()
        self.conv = nn.Conv2d(2 * channels, 2 * channels, 1, bias=False)
        self.norm = nn.BatchNorm2d(2 * channels)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        rows, cols = x.shape[-2:]
        spectrum = torch.fft.rfft2(x.float(), norm="ortho")
        stacked = torch.cat([spectrum.real, spectrum.imag], dim=1)
        stacked = F.relu(self.norm(self.conv(stacked.to(x.dtype))))
        real, imag = stacked.float().chunk(2, dim=1)
        out = torch.fft.irfft2(torch.complex(real, imag), s=(rows, cols), norm="ortho")
        return out.to(x.dtype)


class SpectralTransform(nn.Module):
    """The global branch of an FFC: squeeze, Fourier unit, residual, expand."""

    def __init__(self, channels: int) -> None:
        super().__init__()
        hidden = max(channels // 2, 1)
        self.squeeze = nn.Sequential(
            nn.Conv2d(channels, hidden, 1, bias=False), nn.BatchNorm2d(hidden), nn.ReLU()
        )
        self.fourier = FourierUnit(hidden)
        self.expand = nn.Conv2d(hidden, channels, 1, bias=False)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        squeezed = self.squeeze(x)
        return self.expand(squeezed + self.fourier(squeezed))


class FastFourierConv(nn.Module):
    """FFC: local (3x3) and global (spectral) channel groups exchanging information."""

    def __init__(self, channels: int, global_ratio: float) -> None:
        super().__init__()
        self.n_global = int(round(channels * global_ratio))
        self.n_local = channels - self.n_global
        n_local, n_global = self.n_local, self.n_global
        self.local_to_local = nn.Conv2d(n_local, n_local, 3, padding=1, bias=False)
        self.local_to_global = nn.Conv2d(n_local, n_global, 3, padding=1, bias=False)
        self.global_to_local = nn.Conv2d(n_global, n_local, 3, padding=1, bias=False)
        self.global_to_global = SpectralTransform(n_global)
        self.norm_local = nn.BatchNorm2d(n_local)
        self.norm_global = nn.BatchNorm2d(n_global)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        x_local, x_global = x.split([self.n_local, self.n_global], dim=1)
        out_local = self.local_to_local(x_local) + self.global_to_local(x_global)
        out_global = self.local_to_global(x_local) + self.global_to_global(x_global)
        return torch.cat(
            [F.relu(self.norm_local(out_local)), F.relu(self.norm_global(out_global))], dim=1
        )


class FfcResidualBlock(nn.Module):
    """Two FFCs with a skip connection, as in LaMa's generator."""

    def __init__(self, channels: int, global_ratio: float) -> None:
        super().__init__()
        self.first = FastFourierConv(channels, global_ratio)
        self.second = FastFourierConv(channels, global_ratio)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return x + self.second(self.first(x))


class LamaGenerator(nn.Module):
    """Observed map (one-hot, 3 channels) -> wall logit per cell, at any map size."""

    def __init__(self, config: NetworkConfig) -> None:
        super().__init__()
        self.config = config
        factor, channels = config.downscale, config.channels
        folded = INPUT_CHANNELS * factor * factor
        self.stem = nn.Sequential(
            nn.PixelUnshuffle(factor),
            nn.Conv2d(folded, channels, 3, padding=1, bias=False),
            nn.BatchNorm2d(channels),
            nn.ReLU(),
        )
        self.blocks = nn.Sequential(
            *[FfcResidualBlock(channels, config.global_ratio) for _ in range(config.n_blocks)]
        )
        self.head = nn.Sequential(
            nn.Conv2d(channels, channels, 3, padding=1),
            nn.ReLU(inplace=True),
            nn.Conv2d(channels, factor * factor, 1),
            nn.PixelShuffle(factor),
        )
        refine = config.refine_channels
        self.refine = nn.Sequential(
            nn.Conv2d(INPUT_CHANNELS + 1, refine, 3, padding=1),
            nn.ReLU(inplace=True),  # in place: the full-resolution activations are the largest
            nn.Conv2d(refine, 1, 3, padding=1),
        )
        self.to(memory_format=torch.channels_last)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """float (batch, 3, rows, cols) -> wall logits (batch, 1, rows, cols)."""
        rows, cols = x.shape[-2:]
        factor = self.config.downscale
        pad_rows, pad_cols = (-rows) % factor, (-cols) % factor
        if pad_rows or pad_cols:
            x = F.pad(x, (0, pad_cols, 0, pad_rows))  # zeros: beyond the map's border
        x = x.contiguous(memory_format=torch.channels_last)
        coarse = self.head(self.blocks(self.stem(x)))
        logits = coarse + self.refine(torch.cat([coarse, x], dim=1))
        return logits[..., :rows, :cols]

    def predict_logits(self, x: torch.Tensor) -> torch.Tensor:
        """Inference: float (batch, 3, rows, cols) -> wall logits (batch, 1, rows, cols).

        With `average_turned_view`, the mean of the logits for the map and, turned back,
        for the map turned by 180 degrees. Training crops come in every orientation, but
        the network is not equivariant, so the two views err in different cells and their
        mean is the better map (docs/prediction.md, "The learned ensemble")."""
        if not self.config.average_turned_view:
            return self(x)
        turned = (2, 3)  # flipping rows and columns turns the map by 180 degrees
        return (self(x) + self(x.flip(turned)).flip(turned)) / 2
