"""The image terms of the mapping loss (colour L1, 1 - SSIM, depth L1) as two Triton kernels: the GPU's fused loss.

Through autograd these terms are five grouped convolutions forward and their transposes backward, plus
some twenty full-image elementwise ops, each a kernel and a saved buffer. Here one kernel computes the
three terms of every view of a batch and the SSIM partials, and one more, the gradients with respect to
the rendered colour and depth. A program covers a tile of 22 x 64 output pixels of one view: it blurs
the rows it needs horizontally with the window's taps (shifted loads) and vertically as one matrix
product with a banded (32 x 32) matrix of the taps, so the 11 x 11 window costs two passes, not 121 loads.

Gradient of SSIM (as ``ogmapping.optim.fused_loss``): with mu = G*x, e_xx = G*(x^2), e_xy = G*(x y), G
the zero-padded window (symmetric: its adjoint is itself), dS/dx = G*(dS/dmu) + 2x G*(dS/de_xx) +
y G*(dS/de_xy). The forward kernel stores the three partials; the backward kernel blurs them.

The kernels are ``torch.library.triton_op`` operators with their autograd registered, so a compiled
graph (``ogmapping.mapping.graphs``) traces them as they are. Importing this module needs triton;
with ``TRITON_INTERPRET=1`` set before it is imported (and while they run) the kernels run on CPU
tensors through Triton's interpreter, as the tests run them.
"""

from __future__ import annotations

import torch
import triton
import triton.language as tl
from torch.library import triton_op, wrap_triton

from ogmapping.optim.ssim import C1, C2, WINDOW_SIZE, ReferenceStatistics, gaussian_window, reference_statistics
from ogmapping.runtime.device_constants import on_device

ROWS = 32  # rows a program blurs: its output rows and the window's half on either side
OUT_ROWS = ROWS - (WINDOW_SIZE - 1)  # output rows a program covers
COLS = 64  # output columns a program covers
TAPS = gaussian_window()  # float32, on the CPU; ``_taps`` puts it on a device


@triton.jit
def _shifted(ptr, rows, cols, height, width, shift):
    """The (ROWS, COLS) tile of an (H, W, 3) channel plane at ``rows`` and ``cols + shift``, zero outside."""
    c = cols + shift
    inside = (rows >= 0) & (rows < height) & (c >= 0) & (c < width)
    return tl.load(ptr + (rows * width + c) * 3, mask=inside, other=0.0)


@triton.jit
def _banded_taps(taps_ptr, ROWS: tl.constexpr, WINDOW: tl.constexpr):
    """The vertical blur as a matrix: output row i takes input rows i .. i + WINDOW - 1 with the taps."""
    k = tl.arange(0, ROWS)[None, :] - tl.arange(0, ROWS)[:, None]
    return tl.load(taps_ptr + k, mask=(k >= 0) & (k < WINDOW), other=0.0)


@triton.jit
def _sign(value):
    return tl.where(value > 0, 1.0, 0.0) - tl.where(value < 0, 1.0, 0.0)


@triton.jit
def _program(taps_ptr, height, width, views, ROWS: tl.constexpr, COLS: tl.constexpr, WINDOW: tl.constexpr):
    """This program's view, input rows (ROWS, 1), output rows (ROWS, 1), columns (1, COLS), output mask,
    vertical blur matrix and the stride between the planes of partials."""
    tiles_across = tl.cdiv(width, COLS)
    tile = tl.program_id(0)
    first_row = (tile // tiles_across) * (ROWS - WINDOW + 1)
    offsets = tl.arange(0, ROWS)[:, None]
    rows = first_row + offsets
    cols = (tile % tiles_across) * COLS + tl.arange(0, COLS)[None, :]
    inside = (offsets < ROWS - WINDOW + 1) & (rows < height) & (cols < width)
    band = _banded_taps(taps_ptr, ROWS, WINDOW)
    return tl.program_id(1), rows - WINDOW // 2, rows, cols, inside, band, views * height * width * 3


@triton.jit
def _blurred(ptr, band, in_rows, cols, height, width, taps_ptr,
             ROWS: tl.constexpr, COLS: tl.constexpr, WINDOW: tl.constexpr):
    """The window's blur of an (H, W, 3) channel plane at this program's output pixels."""
    rows_blurred = tl.zeros((ROWS, COLS), tl.float32)
    for k in tl.static_range(WINDOW):
        rows_blurred += tl.load(taps_ptr + k) * _shifted(ptr, in_rows, cols, height, width, k - WINDOW // 2)
    return tl.dot(band, rows_blurred, input_precision="ieee")


@triton.jit
def _forward_kernel(color_ptr, gt_ptr, mean_ptr, square_ptr, depth_ptr, gt_depth_ptr, taps_ptr, partials_ptr,
                    sums_ptr, height, width, views, c1, c2,
                    ROWS: tl.constexpr, COLS: tl.constexpr, WINDOW: tl.constexpr):
    """Per tile: sums of |x - y|, SSIM, valid |d - g| and the valid count; per pixel: dS/d(mu, e_xx, e_xy)."""
    view, in_rows, rows, cols, inside, band, plane = _program(taps_ptr, height, width, views, ROWS, COLS, WINDOW)
    l1 = tl.zeros((ROWS, COLS), tl.float32)
    ssim = tl.zeros((ROWS, COLS), tl.float32)
    for channel in tl.static_range(3):
        base = view * height * width * 3 + channel
        hx = tl.zeros((ROWS, COLS), tl.float32)
        hxx = tl.zeros((ROWS, COLS), tl.float32)
        hxy = tl.zeros((ROWS, COLS), tl.float32)
        for k in tl.static_range(WINDOW):
            tap = tl.load(taps_ptr + k)
            x = _shifted(color_ptr + base, in_rows, cols, height, width, k - WINDOW // 2)
            y = _shifted(gt_ptr + base, in_rows, cols, height, width, k - WINDOW // 2)
            hx += tap * x
            hxx += tap * (x * x)
            hxy += tap * (x * y)
        mx = tl.dot(band, hx, input_precision="ieee")
        exx = tl.dot(band, hxx, input_precision="ieee")
        exy = tl.dot(band, hxy, input_precision="ieee")
        at = base + (rows * width + cols) * 3
        x = tl.load(color_ptr + at, mask=inside, other=0.0)
        y = tl.load(gt_ptr + at, mask=inside, other=0.0)
        my = tl.load(mean_ptr + at, mask=inside, other=0.0)
        eyy = tl.load(square_ptr + at, mask=inside, other=0.0)
        a1 = 2.0 * mx * my + c1
        a2 = 2.0 * (exy - mx * my) + c2
        b1 = mx * mx + my * my + c1
        b2 = (exx - mx * mx) + (eyy - my * my) + c2
        inverse = 1.0 / (b1 * b2)
        s = a1 * a2 * inverse
        # Without dividing by the numerator factors, which can pass through zero.
        d_mean = 2.0 * my * (a2 - a1) * inverse - s * (2.0 * mx / b1 - 2.0 * mx / b2)
        tl.store(partials_ptr + at, d_mean, mask=inside)
        tl.store(partials_ptr + plane + at, -s / b2, mask=inside)
        tl.store(partials_ptr + 2 * plane + at, 2.0 * a1 * inverse, mask=inside)
        ssim += tl.where(inside, s, 0.0)
        l1 += tl.where(inside, tl.abs(x - y), 0.0)
    at = view * height * width + rows * width + cols
    d = tl.load(depth_ptr + at, mask=inside, other=0.0)
    g = tl.load(gt_depth_ptr + at, mask=inside, other=0.0)
    valid = inside & (g > 0) & (g < float("inf"))
    out = sums_ptr + (view * tl.num_programs(0) + tl.program_id(0)) * 4
    tl.store(out, tl.sum(tl.sum(l1, 1), 0))
    tl.store(out + 1, tl.sum(tl.sum(ssim, 1), 0))
    tl.store(out + 2, tl.sum(tl.sum(tl.where(valid, tl.abs(d - g), 0.0), 1), 0))
    tl.store(out + 3, tl.sum(tl.sum(valid.to(tl.float32), 1), 0))


@triton.jit
def _backward_kernel(color_ptr, gt_ptr, depth_ptr, gt_depth_ptr, taps_ptr, partials_ptr, scales_ptr,
                     grad_color_ptr, grad_depth_ptr, height, width, views,
                     ROWS: tl.constexpr, COLS: tl.constexpr, WINDOW: tl.constexpr):
    """Per pixel: d/dx of scale_l1 |x - y| + scale_ssim S and d/dd of scale_depth |d - g| on valid pixels."""
    view, in_rows, rows, cols, inside, band, plane = _program(taps_ptr, height, width, views, ROWS, COLS, WINDOW)
    scale_l1 = tl.load(scales_ptr + view * 3)
    scale_ssim = tl.load(scales_ptr + view * 3 + 1)
    scale_depth = tl.load(scales_ptr + view * 3 + 2)
    for channel in tl.static_range(3):
        base = view * height * width * 3 + channel
        d_mean = _blurred(partials_ptr + base, band, in_rows, cols, height, width, taps_ptr, ROWS, COLS, WINDOW)
        d_square = _blurred(partials_ptr + plane + base, band, in_rows, cols, height, width, taps_ptr, ROWS, COLS,
                            WINDOW)
        d_cross = _blurred(partials_ptr + 2 * plane + base, band, in_rows, cols, height, width, taps_ptr, ROWS, COLS,
                           WINDOW)
        at = base + (rows * width + cols) * 3
        x = tl.load(color_ptr + at, mask=inside, other=0.0)
        y = tl.load(gt_ptr + at, mask=inside, other=0.0)
        grad_ssim = d_mean + 2.0 * x * d_square + y * d_cross
        tl.store(grad_color_ptr + at, scale_ssim * grad_ssim + scale_l1 * _sign(x - y), mask=inside)
    at = view * height * width + rows * width + cols
    d = tl.load(depth_ptr + at, mask=inside, other=0.0)
    g = tl.load(gt_depth_ptr + at, mask=inside, other=0.0)
    valid = (g > 0) & (g < float("inf"))
    tl.store(grad_depth_ptr + at, tl.where(valid, scale_depth * _sign(d - g), 0.0), mask=inside)


def _grid(views: int, height: int, width: int) -> tuple[int, int]:
    return triton.cdiv(height, OUT_ROWS) * triton.cdiv(width, COLS), views


@triton_op("ogmapping::fused_image_terms", mutates_args={})
def _fused_image_terms(color: torch.Tensor, depth: torch.Tensor, gt_color: torch.Tensor, gt_depth: torch.Tensor,
                       mean: torch.Tensor, square_mean: torch.Tensor, taps: torch.Tensor
                       ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """(B, H, W, 3) colours, (B, H, W) depths -> terms (B, 3), SSIM partials (3, B, H, W, 3), valid counts (B,)."""
    views, height, width, _ = color.shape
    grid = _grid(views, height, width)
    partials = color.new_empty((3, *color.shape))
    sums = color.new_empty((views, grid[0], 4))
    wrap_triton(_forward_kernel)[grid](color, gt_color, mean, square_mean, depth, gt_depth, taps, partials, sums,
                                       height, width, views, C1, C2, ROWS=ROWS, COLS=COLS, WINDOW=WINDOW_SIZE)
    totals = sums.sum(dim=1)
    count = height * width * 3
    terms = torch.stack([totals[:, 0] / count, 1.0 - totals[:, 1] / count, totals[:, 2] / totals[:, 3].clamp_min(1)],
                        dim=1)
    return terms, partials, totals[:, 3]


@triton_op("ogmapping::fused_image_terms_backward", mutates_args={})
def _fused_image_terms_backward(grad_terms: torch.Tensor, color: torch.Tensor, depth: torch.Tensor,
                                gt_color: torch.Tensor, gt_depth: torch.Tensor, partials: torch.Tensor,
                                valid: torch.Tensor, taps: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Gradients of the terms' (B, 3) upstream gradients with respect to the rendered colour and depth."""
    views, height, width, _ = color.shape
    count = height * width * 3
    scales = grad_terms * torch.stack([color.new_full((views,), 1.0 / count), color.new_full((views,), -1.0 / count),
                                       1.0 / valid.clamp_min(1)], dim=1)
    grad_color = torch.empty_like(color)
    grad_depth = torch.empty_like(depth)
    wrap_triton(_backward_kernel)[_grid(views, height, width)](
        color, gt_color, depth, gt_depth, taps, partials, scales.contiguous(), grad_color, grad_depth,
        height, width, views, ROWS=ROWS, COLS=COLS, WINDOW=WINDOW_SIZE)
    return grad_color, grad_depth


def _setup_context(ctx, inputs, output) -> None:
    color, depth, gt_color, gt_depth, _, _, taps = inputs
    _, partials, valid = output
    ctx.save_for_backward(color, depth, gt_color, gt_depth, partials, valid, taps)


def _backward(ctx, grad_terms, _grad_partials, _grad_valid):
    color, depth, gt_color, gt_depth, partials, valid, taps = ctx.saved_tensors
    grad_color, grad_depth = _fused_image_terms_backward(grad_terms.contiguous(), color, depth, gt_color, gt_depth,
                                                         partials, valid, taps)
    return grad_color, grad_depth, None, None, None, None, None


_fused_image_terms.register_autograd(_backward, setup_context=_setup_context)


def window_terms(render_color: torch.Tensor, render_depth: torch.Tensor, gt_color: torch.Tensor,
                 gt_depth: torch.Tensor, reference: ReferenceStatistics | None = None) -> torch.Tensor:
    """Colour L1, 1 - mean SSIM and valid-pixel depth L1 of each view of a batch: (B, 3), differentiable in
    the render. Colours (B, H, W, 3) float32 in [0, 1], depths (B, H, W) in metres (gt 0, NaN or inf = no
    measurement); ``reference`` holds ``reference_statistics`` of ``gt_color`` (B, H, W, 3) when cached."""
    if render_color.dim() != 4 or render_color.shape[-1] != 3 or render_color.shape != gt_color.shape:
        raise ValueError(f"the fused loss takes (B, H, W, 3) colours of one shape, got {tuple(render_color.shape)} "
                         f"and {tuple(gt_color.shape)}")
    if render_depth.shape != render_color.shape[:3] or gt_depth.shape != render_depth.shape:
        raise ValueError(f"the fused loss takes (B, H, W) depths matching the colours, got {tuple(render_depth.shape)} "
                         f"and {tuple(gt_depth.shape)}")
    if render_color.dtype != torch.float32:
        raise ValueError(f"the fused loss runs in float32, got {render_color.dtype}")
    if reference is None:
        reference = _batched_statistics(gt_color)
    taps = _taps(render_color.device)
    terms, _, _ = _fused_image_terms(render_color.contiguous(), render_depth.contiguous(), gt_color.contiguous(),
                                     gt_depth.contiguous(), reference.mean.contiguous(),
                                     reference.square_mean.contiguous(), taps)
    return terms


def _taps(device: torch.device) -> torch.Tensor:
    """The window's taps on ``device``: copied there once, or a graph's own constant when compiled."""
    if torch.compiler.is_compiling():
        return TAPS.to(device)
    return on_device(TAPS, device, torch.float32)


def _batched_statistics(gt_color: torch.Tensor) -> ReferenceStatistics:
    """``reference_statistics`` of every view of a (B, H, W, 3) batch, stacked."""
    each = [reference_statistics(view, compiled=False) for view in gt_color]
    mean, square_mean = (torch.stack([getattr(s, name) for s in each]) for name in ("mean", "square_mean"))
    return ReferenceStatistics(gt_color, mean, square_mean)
