"""The fused inference path: a trained `LamaGenerator` rebuilt for fast CPU inference.

Same arithmetic, less work and less memory traffic (docs/benchmarks.md#the-predictor):
batch norms folded into the convolutions, 1x1 convolutions as matrix products, the FFC
channel groups kept apart, the full-resolution refinement in strips of rows that stay in
the CPU's cache, and observed codes one-hot encoded straight into the layouts the network
reads. Its logits equal the training module's to float32 rounding (a test holds every
shipped member to 1e-3 in probability). It runs on PyTorch: ONNX Runtime, OpenVINO and
torch.compile were measured on this network and lost on its FFTs (docs/experiments.md).
"""

from __future__ import annotations

import torch
from torch import nn
from torch.nn import functional as F

from mapex.prediction.network import (
    CODE_CHANNELS,
    OUTSIDE_MAP,
    FastFourierConv,
    FourierUnit,
    LamaGenerator,
    SpectralTransform,
)

DEFAULT_STRIP_ROWS = 32  # refinement rows per strip: the fastest of 8..128 (measured, 2 MB L2)


def fold_batch_norm(
    weight: torch.Tensor, bias: torch.Tensor | None, norm: nn.BatchNorm2d
) -> tuple[torch.Tensor, torch.Tensor]:
    """The weight and bias of one convolution that computes conv-then-`norm` (evaluation
    mode)."""
    scale = norm.weight / torch.sqrt(norm.running_var + norm.eps)
    shift = norm.bias - norm.running_mean * scale
    if bias is not None:
        shift = shift + bias * scale
    return weight * scale.view(-1, *([1] * (weight.dim() - 1))), shift


def _frozen(tensor: torch.Tensor, channels_last: bool = True) -> nn.Parameter:
    tensor = tensor.detach().clone()
    if channels_last and tensor.dim() == 4:
        tensor = tensor.contiguous(memory_format=torch.channels_last)
    return nn.Parameter(tensor, requires_grad=False)


class FusedConv(nn.Module):
    """A convolution (weight, bias, padding), optionally followed by ReLU."""

    def __init__(
        self,
        weight: torch.Tensor,
        bias: torch.Tensor | None,
        padding: int | tuple[int, int],
        relu: bool,
    ) -> None:
        super().__init__()
        self.weight = _frozen(weight)
        self.bias = None if bias is None else _frozen(bias)
        self.padding = padding
        self.relu = relu

    @classmethod
    def of(cls, conv: nn.Conv2d, norm: nn.BatchNorm2d | None = None, relu: bool = False):
        """`conv` (then `norm`, then ReLU) as one fused convolution."""
        weight, bias = conv.weight, conv.bias
        if norm is not None:
            weight, bias = fold_batch_norm(weight, bias, norm)
        return cls(weight, bias, conv.padding[0], relu)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        if self.weight.shape[-2:] == (1, 1):
            # a 1x1 convolution is a matrix product over the channels of the NHWC memory
            # (oneDNN sends channels-last 1x1 convolutions down PyTorch's slow path)
            matrix = self.weight[:, :, 0, 0]
            out = F.linear(x.permute(0, 2, 3, 1), matrix, self.bias).permute(0, 3, 1, 2)
        else:
            out = F.conv2d(x, self.weight, self.bias, padding=self.padding)
        return F.relu_(out) if self.relu else out


class FusedFourierUnit(nn.Module):
    """`FourierUnit` with its batch norm folded; the 1x1 convolution as a matrix product."""

    def __init__(self, unit: FourierUnit) -> None:
        super().__init__()
        weight, bias = fold_batch_norm(unit.conv.weight, unit.conv.bias, unit.norm)
        self.weight = _frozen(weight[:, :, 0, 0], channels_last=False)
        self.bias = _frozen(bias[:, None], channels_last=False)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        batch, channels, rows, cols = x.shape
        spectrum = torch.fft.rfft2(x.float().contiguous(), norm="ortho")
        stacked = torch.cat([spectrum.real, spectrum.imag], dim=1).flatten(2)
        mixed = F.relu_(torch.baddbmm(self.bias, self.weight.expand(batch, -1, -1), stacked))
        real, imag = mixed.float().view(batch, 2 * channels, *spectrum.shape[-2:]).chunk(2, dim=1)
        out = torch.fft.irfft2(torch.complex(real, imag), s=(rows, cols), norm="ortho")
        return out.to(x.dtype)


class FusedSpectralTransform(nn.Module):
    """`SpectralTransform` with folded batch norms; its expansion returned unbiased, so the
    caller can fold the next batch norm into it."""

    def __init__(self, spectral: SpectralTransform, expand: FusedConv) -> None:
        super().__init__()
        conv, norm, _ = spectral.squeeze
        self.squeeze = FusedConv.of(conv, norm, relu=True)
        self.fourier = FusedFourierUnit(spectral.fourier)
        self.expand = expand

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        squeezed = self.squeeze(x)
        return self.expand(squeezed.add_(self.fourier(squeezed)))


class FusedFastFourierConv(nn.Module):
    """`FastFourierConv` with both output batch norms folded into the convolutions that
    feed them (each branch's sum is linear, so the norm's scale goes to every addend and
    its shift to one)."""

    def __init__(self, ffc: FastFourierConv) -> None:
        super().__init__()
        self.n_local, self.n_global = ffc.n_local, ffc.n_global
        self.local_to_local = FusedConv.of(ffc.local_to_local, ffc.norm_local)
        self.global_to_local = _scaled(ffc.global_to_local, ffc.norm_local)
        self.local_to_global = FusedConv.of(ffc.local_to_global, ffc.norm_global)
        expand = _scaled(ffc.global_to_global.expand, ffc.norm_global)
        self.global_to_global = FusedSpectralTransform(ffc.global_to_global, expand)

    def forward(
        self, x_local: torch.Tensor, x_global: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """The local and global channel groups, kept apart (no split, no concatenation)."""
        out_local = self.local_to_local(x_local).add_(self.global_to_local(x_global))
        out_global = self.local_to_global(x_local).add_(self.global_to_global(x_global))
        return F.relu_(out_local), F.relu_(out_global)


class SingleOutputConv(nn.Module):
    """A 3x3 convolution to one channel (rows unpadded, columns zero-padded) as one matrix
    product, channels to the nine taps, and nine shifted sums of the tap planes: oneDNN
    computes a single output channel 2.4 times slower (0.50 against 0.21 ms a strip)."""

    def __init__(self, conv: nn.Conv2d) -> None:
        super().__init__()
        if conv.weight.shape[0] != 1 or conv.weight.shape[-2:] != (3, 3):
            raise ValueError(f"a 3x3 convolution to one channel, not {tuple(conv.weight.shape)}")
        self.taps = _frozen(conv.weight[0].permute(1, 2, 0).reshape(9, -1), channels_last=False)
        self.bias = _frozen(conv.bias, channels_last=False)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """channels-last (batch, channels, rows + 2, cols) -> (batch, 1, rows, cols)."""
        batch, channels, rows, cols = x.shape
        pixels = x.permute(0, 2, 3, 1).reshape(batch, rows * cols, channels)
        planes = torch.matmul(self.taps, pixels.transpose(1, 2)).view(batch, 9, rows, cols)
        planes = F.pad(planes, (1, 1))
        out = self.bias.view(1, 1, 1).expand(batch, rows - 2, cols).clone()
        for tap in range(9):
            row, col = divmod(tap, 3)
            out += planes[:, tap, row : row + rows - 2, col : col + cols]
        return out[:, None]


def _one_hot(codes: torch.Tensor, dim: int) -> torch.Tensor:
    """float32 one-hot of `codes` along a new dimension `dim`: free, occupied, unknown, as
    `encode_observed` (any other code, OUTSIDE_MAP, all zeros)."""
    return torch.stack([codes == code for code in CODE_CHANNELS], dim=dim).float()


def _unshuffled_one_hot(codes: torch.Tensor, factor: int) -> torch.Tensor:
    """`nn.PixelUnshuffle(factor)(encode_observed(codes))`, channels-last: the codes are
    reordered (one byte a cell), then one-hot encoded in place in the stem's layout."""
    batch, rows, cols = codes.shape
    blocks = codes.view(batch, rows // factor, factor, cols // factor, factor)
    blocks = blocks.permute(0, 1, 3, 2, 4)  # (batch, rows/f, cols/f, f, f)
    nhwc = _one_hot(blocks, dim=3).reshape(batch, rows // factor, cols // factor, -1)
    return nhwc.permute(0, 3, 1, 2)


def _scaled(conv: nn.Conv2d, norm: nn.BatchNorm2d) -> FusedConv:
    """`conv` times `norm`'s scale, without its shift (which the other addend carries)."""
    weight, _ = fold_batch_norm(conv.weight, None, norm)
    return FusedConv(weight, None, conv.padding[0], relu=False)


class FusedGenerator(nn.Module):
    """A `LamaGenerator`'s forward pass for inference: same logits, less time."""

    def __init__(self, model: LamaGenerator, strip_rows: int = DEFAULT_STRIP_ROWS) -> None:
        super().__init__()
        if strip_rows < 1:
            raise ValueError(f"strip_rows must be >= 1, not {strip_rows}")
        self.config = model.config
        self.strip_rows = strip_rows
        _, conv, norm, _ = model.stem
        self.stem = FusedConv.of(conv, norm, relu=True)
        self.n_local = model.blocks[0].first.n_local
        self.blocks = nn.ModuleList(
            nn.ModuleList([FusedFastFourierConv(block.first), FusedFastFourierConv(block.second)])
            for block in model.blocks
        )
        head_conv, _, head_out, self.shuffle = model.head
        self.head_conv = FusedConv.of(head_conv, relu=True)
        self.head_out = FusedConv.of(head_out)
        refine_in, _, refine_out = model.refine
        # rows come from the strip's halo, columns from the convolutions' own zero padding
        self.refine_in = FusedConv(refine_in.weight, refine_in.bias, padding=(0, 1), relu=True)
        self.refine_out = SingleOutputConv(refine_out)
        self.eval()

    def forward(self, codes: torch.Tensor) -> torch.Tensor:
        """Observed codes uint8 (batch, rows, cols) -> wall logits (batch, 1, rows, cols): the
        training module's logits for `encode_observed(codes)`. Codes go in as they are, and
        are one-hot encoded straight into the layouts the stem and the refinement read, so
        no full-resolution float image is made, padded and reordered."""
        batch, rows, cols = codes.shape
        factor = self.config.downscale
        if rows % factor or cols % factor:  # OUTSIDE_MAP encodes as zeros: beyond the border
            padding = (0, (-cols) % factor, 0, (-rows) % factor)
            codes = F.pad(codes, padding, value=int(OUTSIDE_MAP))
        trunk = self.stem(_unshuffled_one_hot(codes, factor))
        local, global_ = (
            part.contiguous(memory_format=torch.channels_last)
            for part in trunk.split([self.n_local, trunk.shape[1] - self.n_local], dim=1)
        )
        for first, second in self.blocks:
            new_local, new_global = second(*first(local, global_))
            local, global_ = local.add_(new_local), global_.add_(new_global)
        trunk = torch.cat([local, global_], dim=1)
        coarse = self.shuffle(self.head_out(self.head_conv(trunk)))
        return self._refined(coarse, codes)[..., :rows, :cols]

    def predict_logits(self, codes: torch.Tensor) -> torch.Tensor:
        """As `LamaGenerator.predict_logits`, from codes (batch, rows, cols): one view, or
        the mean of the map's and its 180-degree turn's (`average_turned_view`)."""
        if not self.config.average_turned_view:
            return self(codes)
        return (self(codes) + self(codes.flip((1, 2))).flip((2, 3))) / 2

    def _refined(self, coarse: torch.Tensor, codes: torch.Tensor) -> torch.Tensor:
        """coarse + refine(cat(coarse, x)), `strip_rows` output rows at a time. The two 3x3
        convolutions need two rows of input on either side of a strip; rows beyond the
        map's edge are zeros, for the input and for the hidden layer alike."""
        batch, _, rows, cols = coarse.shape
        halo = 2
        logits = torch.empty_like(coarse, memory_format=torch.contiguous_format)
        for start in range(0, rows, self.strip_rows):
            stop = min(start + self.strip_rows, rows)
            first, last = max(start - halo, 0), min(stop + halo, rows)  # input rows in the map
            piece = coarse.new_zeros(batch, stop - start + 2 * halo, cols, 1 + len(CODE_CHANNELS))
            at = first - (start - halo)
            piece[:, at : at + last - first, :, :1] = coarse[:, :, first:last].permute(0, 2, 3, 1)
            piece[:, at : at + last - first, :, 1:] = _one_hot(codes[:, first:last, :cols], -1)
            hidden = self.refine_in(piece.permute(0, 3, 1, 2))
            if start == 0:
                hidden[:, :, 0] = 0  # the hidden layer's row above the map
            if stop == rows:
                hidden[:, :, -1] = 0  # and below it
            logits[:, :, start:stop] = coarse[:, :, start:stop] + self.refine_out(hidden)
        return logits
