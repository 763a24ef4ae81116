"""OccWorld's scene tokenizer (section 3.2): a VQ-VAE over a 3-class occupancy grid.

Each voxel's class (free, occupied, unknown) gets a learnable embedding of ``expansion``
channels; the ``nz`` heights are folded into the channels, giving a BEV image of ``nz *
expansion`` channels. A 2-D encoder of residual blocks (GroupNorm, swish) down-samples it by
``2 ** (levels - 1)``, with self-attention at the token resolution and in the middle block;
each token is quantized to its nearest code; the decoder mirrors the encoder (nearest
up-sampling and a 3x3 convolution per level), its output is split back into ``nz`` heights of
``expansion`` channels and each voxel's class logits are the dot products with the class
embeddings (the public implementation's classifier). Unknown is an input class and an
ignored target: the loss is ``ce_weight`` x cross entropy + ``lovasz_weight`` x Lovasz-softmax
over the labelled (free or occupied) voxels, + ``vq_weight`` x the VQ loss
``|sg[c] - z|^2 + beta |c - sg[z]|^2`` (the public configuration's form, beta 1).

Parameter count of ``paper`` (``PAPER_PARAMETERS``, checked by the tests), from the public
configuration (ch 64, multipliers 1, 2, 4, 2 blocks per level, attention at 50 x 50, 16 x 8 =
128 input and output channels, 128-channel codes, 512 codes), with conv(k, i, o) = k*k*i*o + o,
GN(c) = 2c, RB(i, o) = GN(i) + conv(3, i, o) + GN(o) + conv(3, o, o) [+ conv(1, i, o) if i != o],
AT(c) = GN(c) + 4 conv(1, c, c):

    class embedding            3 x 8                                         =        24
    encoder  conv_in           conv(3, 128, 64)                              =    73,792
             level 1 (200^2)   2 RB(64, 64)                                  =   148,224
             down              conv(3, 64, 64)                               =    36,928
             level 2 (100^2)   RB(64, 128) + RB(128, 128)                    =   525,824
             down              conv(3, 128, 128)                             =   147,584
             level 3 (50^2)    RB(128, 256) + RB(256, 256) + 2 AT(256)       = 2,627,584
             middle            2 RB(256, 256) + AT(256)                      = 2,626,048
             out               GN(256) + conv(3, 256, 128)                   =   295,552
    quantizer                  conv(1, 128, 128) x 2 + 512 x 128             =    98,560
    decoder  conv_in           conv(3, 128, 256)                             =   295,168
             middle            2 RB(256, 256) + AT(256)                      = 2,626,048
             level 3 (50^2)    2 RB(256, 256) + 2 AT(256)                    = 2,889,728
             up                conv(3, 256, 256)                             =   590,080
             level 2 (100^2)   RB(256, 128) + RB(128, 128)                   =   771,968
             up                conv(3, 128, 128)                             =   147,584
             level 1 (200^2)   RB(128, 64) + RB(64, 64)                      =   193,472
             out               GN(64) + conv(3, 64, 128)                     =    73,984
                                                                               ----------
                                                                               14,168,152

(the public model has 18 semantic classes, 18 x 8 = 144 embedding parameters instead of 24).
Ours adds, with ``surface`` not ``none`` (the methods' default), the sub-voxel planes' offset head:
conv(3, 64, 16) = 9,232 parameters (``OFFSET_HEAD_PARAMETERS`` for ``paper``).
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

from pcfbench.errors import PcfbenchError
from pcfbench.methods.occworld.config import TokenizerConfig
from pcfbench.methods.occworld.occupancy import FREE, UNKNOWN

#: ``paper``'s parameter count, derived by hand in the module docstring
PAPER_PARAMETERS = 14_168_152
#: the offset head ``paper`` adds with ``surface`` (ours): conv(3, 64, 16)
OFFSET_HEAD_PARAMETERS = 9 * 64 * 16 + 16


def _norm(c: int) -> nn.GroupNorm:
    return nn.GroupNorm(32 if c > 32 else max(1, c // 4), c, eps=1e-6)


class ResBlock(nn.Module):
    def __init__(self, cin: int, cout: int) -> None:
        super().__init__()
        self.norm1, self.conv1 = _norm(cin), nn.Conv2d(cin, cout, 3, padding=1)
        self.norm2, self.conv2 = _norm(cout), nn.Conv2d(cout, cout, 3, padding=1)
        self.skip = nn.Conv2d(cin, cout, 1) if cin != cout else nn.Identity()

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        h = self.conv1(F.silu(self.norm1(x)))
        h = self.conv2(F.silu(self.norm2(h)))
        return self.skip(x) + h


class Attention(nn.Module):
    """Single-head self-attention over the positions of a feature map, residual."""

    def __init__(self, c: int) -> None:
        super().__init__()
        self.norm = _norm(c)
        self.q, self.k, self.v, self.proj = (nn.Conv2d(c, c, 1) for _ in range(4))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        B, C, H, W = x.shape
        h = self.norm(x)
        q, k, v = (f(h).flatten(2).transpose(1, 2) for f in (self.q, self.k, self.v))  # (B, HW, C)
        o = F.scaled_dot_product_attention(q, k, v)
        return x + self.proj(o.transpose(1, 2).reshape(B, C, H, W))


class Encoder(nn.Module):
    def __init__(self, cfg: TokenizerConfig) -> None:
        super().__init__()
        c_in = cfg.dims[2] * cfg.expansion
        self.conv_in = nn.Conv2d(c_in, cfg.ch, 3, padding=1)
        levels = len(cfg.ch_mult)
        self.blocks, self.attns, self.downs = nn.ModuleList(), nn.ModuleList(), nn.ModuleList()
        c = cfg.ch
        for i, m in enumerate(cfg.ch_mult):
            blocks, attns = nn.ModuleList(), nn.ModuleList()
            for _ in range(cfg.num_res_blocks):
                blocks.append(ResBlock(c, cfg.ch * m))
                c = cfg.ch * m
                attns.append(Attention(c) if i == levels - 1 and cfg.level_attention else nn.Identity())  # tokens
            self.blocks.append(blocks)
            self.attns.append(attns)
            self.downs.append(nn.Conv2d(c, c, 3, stride=2, padding=1) if i < levels - 1 else nn.Identity())
        self.mid = nn.Sequential(ResBlock(c, c), Attention(c), ResBlock(c, c))
        self.norm_out, self.conv_out = _norm(c), nn.Conv2d(c, cfg.z_channels, 3, padding=1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        h = self.conv_in(x)
        for blocks, attns, down in zip(self.blocks, self.attns, self.downs):
            for b, a in zip(blocks, attns):
                h = a(b(h))
            h = down(h)
        h = self.mid(h)
        return self.conv_out(F.silu(self.norm_out(h)))


class Decoder(nn.Module):
    def __init__(self, cfg: TokenizerConfig) -> None:
        super().__init__()
        levels = len(cfg.ch_mult)
        c = cfg.ch * cfg.ch_mult[-1]
        self.conv_in = nn.Conv2d(cfg.z_channels, c, 3, padding=1)
        self.mid = nn.Sequential(ResBlock(c, c), Attention(c), ResBlock(c, c))
        self.blocks, self.attns, self.ups = nn.ModuleList(), nn.ModuleList(), nn.ModuleList()
        for i in reversed(range(levels)):
            blocks, attns = nn.ModuleList(), nn.ModuleList()
            for _ in range(cfg.num_res_blocks):
                blocks.append(ResBlock(c, cfg.ch * cfg.ch_mult[i]))
                c = cfg.ch * cfg.ch_mult[i]
                attns.append(Attention(c) if i == levels - 1 and cfg.level_attention else nn.Identity())
            self.blocks.append(blocks)
            self.attns.append(attns)
            self.ups.append(nn.Conv2d(c, c, 3, padding=1) if i > 0 else nn.Identity())
        self.norm_out = _norm(c)
        self.conv_out = nn.Conv2d(c, cfg.dims[2] * cfg.expansion, 3, padding=1)

    def features(self, z: torch.Tensor) -> torch.Tensor:
        """The activations the output convolutions read (B, ch, X, Y)."""
        h = self.mid(self.conv_in(z))
        for blocks, attns, up in zip(self.blocks, self.attns, self.ups):
            for b, a in zip(blocks, attns):
                h = a(b(h))
            if isinstance(up, nn.Conv2d):
                h = up(F.interpolate(h, scale_factor=2.0, mode="nearest"))
        return F.silu(self.norm_out(h))

    def forward(self, z: torch.Tensor) -> torch.Tensor:
        return self.conv_out(self.features(z))


class VectorQuantizer(nn.Module):
    """The public configuration's 1x1 convolutions around Copilot4D's quantizer (nearest code,
    straight-through, ``|sg[c] - z|^2 + beta |c - sg[z]|^2``, and its dead-code K-means
    re-initialisation: ``maybe_reinit`` after each training step)."""

    def __init__(self, cfg: TokenizerConfig) -> None:
        super().__init__()
        from pcfbench.methods.copilot4d.model import VectorQuantizer as CodebookQuantizer

        self.quant_conv = nn.Conv2d(cfg.z_channels, cfg.z_channels, 1)
        self.post_quant_conv = nn.Conv2d(cfg.z_channels, cfg.z_channels, 1)
        self.core = CodebookQuantizer(cfg)

    @property
    def codebook(self) -> torch.Tensor:
        """(codebook_size, z_channels) code vectors."""
        return self.core.codebook

    def codes(self, z: torch.Tensor) -> torch.Tensor:
        """(B, C, h, w) pre-quantization features -> (B, h, w) nearest code indices."""
        return self.core.codes_for(z.permute(0, 2, 3, 1))

    def embed(self, codes: torch.Tensor) -> torch.Tensor:
        """(B, h, w) codes -> (B, C, h, w) code vectors."""
        return self.core.lookup(codes).permute(0, 3, 1, 2)

    def forward(self, z: torch.Tensor):
        """Quantize the encoder's output: (codes, straight-through code vectors, VQ loss)."""
        z_st, codes, loss = self.core(self.quant_conv(z).permute(0, 2, 3, 1))
        return codes, z_st.permute(0, 3, 1, 2), loss


class SceneTokenizer(nn.Module):
    def __init__(self, cfg: TokenizerConfig) -> None:
        super().__init__()
        self.cfg = cfg
        self.class_embed = nn.Embedding(cfg.num_classes, cfg.expansion)
        self.encoder = Encoder(cfg)
        self.vq = VectorQuantizer(cfg)
        self.decoder = Decoder(cfg)
        # the sub-voxel planes' offsets (ours; surface.py): one per voxel, in units of cfg.offset_scale
        self.offset_out = (nn.Conv2d(cfg.ch * cfg.ch_mult[0], cfg.dims[2], 3, padding=1)
                           if cfg.surface != "none" else None)

    def bev(self, labels: torch.Tensor) -> torch.Tensor:
        """(B, X, Y, Z) class labels -> (B, Z * expansion, X, Y): heights folded into channels."""
        B, X, Y, Z = labels.shape
        return self.class_embed(labels.long()).reshape(B, X, Y, Z * self.cfg.expansion).permute(0, 3, 1, 2)

    def encode(self, labels: torch.Tensor):
        """(codes (B, h, w), straight-through code vectors, VQ loss) of (B, X, Y, Z) labels."""
        return self.vq(self.encoder(self.bev(labels)))

    def tokenize(self, labels: torch.Tensor) -> torch.Tensor:
        return self.vq.codes(self.vq.quant_conv(self.encoder(self.bev(labels))))

    def decode_all(self, quantized: torch.Tensor):
        """(B, C, h, w) code vectors -> ((B, X, Y, Z, classes) logits, (B, X, Y, Z) plane
        offsets in metres, or None without the offset head)."""
        h = self.decoder.features(self.vq.post_quant_conv(quantized))
        out = self.decoder.conv_out(h)
        B, _, X, Y = out.shape
        feat = out.view(B, self.cfg.dims[2], self.cfg.expansion, X, Y).permute(0, 3, 4, 1, 2)
        offsets = None
        if self.offset_out is not None:
            offsets = self.offset_out(h).permute(0, 2, 3, 1) * self.cfg.offset_scale
        return feat @ self.class_embed.weight.T, offsets

    def decode(self, quantized: torch.Tensor) -> torch.Tensor:
        """(B, C, h, w) code vectors -> (B, X, Y, Z, classes) logits."""
        return self.decode_all(quantized)[0]

    def decode_codes(self, codes: torch.Tensor) -> torch.Tensor:
        return self.decode(self.vq.embed(codes))

    def forward(self, labels: torch.Tensor):
        codes, quantized, l_vq = self.encode(labels)
        return self.decode(quantized), codes, l_vq


def occupancy_probability(logits: torch.Tensor) -> torch.Tensor:
    """(..., classes) logits -> (...) probability that the voxel is not free: 1 - p(free)."""
    return 1.0 - torch.softmax(logits.float(), dim=-1)[..., FREE]


def lovasz_softmax(probs: torch.Tensor, labels: torch.Tensor, ignore: int = UNKNOWN) -> torch.Tensor:
    """Lovasz-softmax (Berman et al. 2018, the classes present): (N, C) probabilities and (N,)
    labels, ``ignore`` left out; the mean over the classes present of the Lovasz extension of
    the Jaccard loss at the errors ``|[label = c] - p_c|``. 0 when no voxel is labelled."""
    keep = labels != ignore
    probs, labels = probs[keep], labels[keep]
    losses = []
    for c in range(probs.shape[1]):
        fg = (labels == c).to(probs.dtype)
        if fg.sum() == 0:
            continue
        err, order = (fg - probs[:, c]).abs().sort(descending=True)
        fg = fg[order]
        gts = fg.sum()
        jac = 1.0 - (gts - fg.cumsum(0)) / (gts + (1.0 - fg).cumsum(0))
        grad = torch.cat([jac[:1], jac[1:] - jac[:-1]])
        losses.append(err @ grad)
    return torch.stack(losses).mean() if losses else probs.sum() * 0.0


def tokenizer_losses(model: SceneTokenizer, labels: torch.Tensor,
                     offsets: torch.Tensor | None = None) -> dict[str, torch.Tensor]:
    """One step's losses on (B, X, Y, Z) labels (and, with the offset head, their planes'
    (B, X, Y, Z) ``offsets`` in metres): ``loss`` (the weighted sum), ``ce``, ``lovasz``,
    ``vq``, ``offset`` (the mean absolute offset error over the occupied voxels, in units of
    ``cfg.offset_scale``; 0 without the head), ``accuracy`` (of the labelled voxels) and ``codes``."""
    from pcfbench.methods.occworld.occupancy import OCCUPIED

    cfg = model.cfg
    if (offsets is None) != (model.offset_out is None):
        raise PcfbenchError(f"occworld tokenizer {cfg.name!r} (surface={cfg.surface}): "
                            + ("its offset head needs the planes' offsets" if offsets is None
                               else "offsets given to a tokenizer without an offset head"))
    codes, quantized, l_vq = model.encode(labels)
    logits, pred_off = model.decode_all(quantized)
    flat = logits.reshape(-1, cfg.num_classes).float()
    target = labels.reshape(-1).long()
    valid = target != UNKNOWN
    ce = F.cross_entropy(flat, target, ignore_index=UNKNOWN) if valid.any() else flat.sum() * 0.0
    lov = lovasz_softmax(torch.softmax(flat, dim=1), target)
    loss = cfg.ce_weight * ce + cfg.lovasz_weight * lov + cfg.vq_weight * l_vq.float()
    l_off = flat.sum() * 0.0
    if pred_off is not None:
        occ = labels == OCCUPIED
        if occ.any():
            l_off = ((pred_off.float() - offsets.float()).abs()[occ]).mean() / cfg.offset_scale
        loss = loss + cfg.offset_weight * l_off
    with torch.no_grad():
        acc = (flat.argmax(1)[valid] == target[valid]).float().mean() if valid.any() else flat.new_tensor(float("nan"))
    return {"loss": loss, "ce": ce, "lovasz": lov, "vq": l_vq.float(), "offset": l_off, "accuracy": acc,
            "codes": codes}


def count_parameters(model: nn.Module) -> int:
    return sum(p.numel() for p in model.parameters())
