"""HiveFormer's block-causal transformer: each keyframe's tokens attend to the instruction and to the tokens of
every earlier keyframe of its episode (`BlockCausalLayer`), then to each other; run packed over a window's real
steps, one attention call per step ordinal, or with a mask for a rollout's newest step.
"""

from dataclasses import dataclass

import torch
import torch.nn.functional as F  # noqa: N812
from torch import Tensor, nn

from .configuration_hiveformer import HiveformerConfig

# The head dimension below which attention is zero-padded on CPU (see MultiHeadAttention).
FUSED_CPU_MIN_HEAD_DIM = 16


class Dropout(nn.Dropout):
    """`nn.Dropout` (same rule, same scaling) whose mask comes from uniform draws: PyTorch's CPU dropout
    draws it with `bernoulli_`, about twice as slow (docs/plugin.md). On other devices, PyTorch's."""

    def forward(self, x: Tensor) -> Tensor:
        if not self.training or self.p == 0 or x.device.type != "cpu":
            return super().forward(x)
        keep = torch.empty_like(x).uniform_().ge_(self.p).mul_(1 / (1 - self.p))  # 0 or 1 / (1 - p)
        return x * keep


class MultiHeadAttention(nn.Module):
    def __init__(self, dim: int, num_heads: int, dropout: float):
        super().__init__()
        self.num_heads = num_heads
        self.dropout = dropout
        self.query = nn.Linear(dim, dim)
        self.key_value = nn.Linear(dim, 2 * dim)
        self.out = nn.Linear(dim, dim)

    def forward(self, queries: Tensor, keys: Tensor, allowed: Tensor | None = None) -> Tensor:
        """queries (B, S, D), keys (B, K, D), allowed (B, 1, S, K) bool or None (all) -> (B, S, D)."""
        q = self._heads(self.query(queries))
        k, v = self._heads(self.key_value(keys), 2)
        return self._output(self._attend(q, k, v, allowed), queries.shape)

    def block_causal(self, x: Tensor, instruction: Tensor, instruction_mask: Tensor, packing: "PackedSteps",
                     use_history: bool = True) -> Tensor:
        """Every packed step's tokens attend to its sample's instruction and to the tokens of its sample's
        steps up to its own (its own only without history): x (M, N, D) packed as `packing` -> (M, N, D).

        The same as `forward` with `block_causal_mask` over the padded (B, T) window, computed block by block:
        one attention call per step ordinal r, whose queries are the r-th steps of the samples that have
        one and whose keys are those samples' instruction and steps 0..r. It skips the masked blocks
        (about half the window's scores) and the padding steps, which the masked form computes and throws
        away: a tower training step's attention kernels (history 25, batch 16) take 0.2 s instead of 1.0 s.
        """
        steps, per_step = len(packing.counts), x.shape[1]
        q = self._heads(self.query(x))  # (M, heads, N, head_dim)
        kv, instruction_kv = self.key_value(x), self.key_value(instruction)  # (M, N, 2D), (B, L, 2D)
        key_mask = None if bool(instruction_mask.all()) else instruction_mask
        if not use_history:  # every step on its own: its instruction and its own tokens, one call for all
            k, v = self._heads(torch.cat([instruction_kv[packing.sample], kv], dim=1), 2)
            if key_mask is not None:
                key_mask = F.pad(key_mask[packing.sample], (0, per_step), value=True)[:, None, None, :]
            return self._output(self._attend(q, k, v, key_mask), x.shape)
        # Keys of each sample (ranked as `packing`): its instruction, then its steps in order; positions past
        # a sample's last step stay zero and no query reaches them.
        rows = packing.rank * steps + packing.ordinal  # each packed step's row of the ranked samples' B*T steps
        aligned = kv.new_zeros(packing.batch * steps, *kv.shape[1:]).index_copy(0, rows, kv)
        aligned = aligned.view(packing.batch, -1, kv.shape[-1])  # (B, T*N, 2D)
        keys = torch.cat([instruction_kv[packing.order], aligned], dim=1)  # (B, L + T*N, 2D)
        k, v = self._heads(keys, 2)  # (B, heads, L + T*N, head_dim)
        length = instruction.shape[1]
        bounds = [(count, length + (ordinal + 1) * per_step) for ordinal, count in enumerate(packing.counts)]
        if key_mask is not None:
            key_mask = F.pad(key_mask[packing.order], (0, steps * per_step), value=True)[:, None, None, :]
        masks = [None if key_mask is None else key_mask[:count, ..., :stop] for count, stop in bounds]
        queries = q.split(packing.counts)  # the r-th steps of the samples that have one
        inputs = zip(queries, KeyPrefixes.apply(k, bounds), KeyPrefixes.apply(v, bounds), masks, strict=True)
        return self._output(torch.cat([self._attend(*call) for call in inputs]), x.shape)

    def _heads(self, x: Tensor, parts: int = 1) -> Tensor | tuple[Tensor, ...]:
        """(B, S, parts * D) -> `parts` tensors (B, heads, S, head_dim), zero-padded to FUSED_CPU_MIN_HEAD_DIM
        on CPU where no gradient is taken (rollouts): PyTorch's fused CPU kernel is slow at head dimensions under
        16 (the paper's is 8), and zero columns in queries, keys and values change no score and no output (a
        rollout's cross-attention, 193 queries x 1,170 keys: ~1.4x faster). A training step keeps the heads as
        they are: there the kernels' forward and backward passes are no slower at 8, and the padding's copies,
        zero-fills and gradient slices cost ~20 ms of a `make reference` step (docs/benchmarks.md)."""
        head_dim = x.shape[-1] // (parts * self.num_heads)
        heads = x.unflatten(-1, (parts, self.num_heads, head_dim)).movedim(-3, 1).transpose(-2, -3)
        inference = x.device.type == "cpu" and not x.requires_grad and not self._dropout_p()
        padding = FUSED_CPU_MIN_HEAD_DIM - head_dim if inference else 0
        if padding > 0:
            heads = F.pad(heads, (0, padding))  # (B, parts, heads, S, hd)
        return heads[:, 0] if parts == 1 else heads.unbind(1)

    def _dropout_p(self) -> float:
        return self.dropout if self.training else 0.0

    def _attend(self, q: Tensor, k: Tensor, v: Tensor, allowed: Tensor | None) -> Tensor:
        """Without dropout on the attention weights PyTorch's fused kernel runs on CPU and GPU; with it,
        CPU falls back to materialising the (B, heads, S, K) weights (see attention_dropout)."""
        head_dim = self.out.in_features // self.num_heads
        return F.scaled_dot_product_attention(q, k, v, attn_mask=allowed, dropout_p=self._dropout_p(),
                                              scale=head_dim**-0.5)

    def _output(self, attended: Tensor, shape: torch.Size) -> Tensor:
        """(..., heads, S, padded head_dim) -> (..., S, D) through the output projection."""
        head_dim = shape[-1] // self.num_heads
        return self.out(attended[..., :head_dim].transpose(-2, -3).reshape(shape))


class KeyPrefixes(torch.autograd.Function):
    """keys (B, heads, S, hd) -> the views keys[:count, :, :stop] for each (count, stop) of `bounds`.

    The backward pass adds each view's gradient into one zeroed buffer. Sliced one by one, each view's
    backward pass would allocate and zero-fill a gradient of the keys' full size to be added to the others:
    for a tower window of 25 steps, 25 such buffers (~40 MB each) for the keys and as many for the values.
    """

    @staticmethod
    def forward(ctx, keys: Tensor, bounds: list[tuple[int, int]]) -> tuple[Tensor, ...]:
        ctx.bounds, ctx.like = bounds, {"size": keys.shape, "dtype": keys.dtype, "device": keys.device}
        ctx.set_materialize_grads(False)  # a view without gradient adds nothing
        return tuple(keys[:count, :, :stop] for count, stop in bounds)

    @staticmethod
    def backward(ctx, *grads: Tensor):
        total = torch.zeros(**ctx.like)
        for (count, stop), grad in zip(ctx.bounds, grads, strict=True):
            if grad is not None:
                total[:count, :, :stop] += grad
        return total, None


@dataclass
class PackedSteps:
    """The real steps of a (B, T) window, packed step-major: all samples' first steps, then their second...

    Samples are ranked by their number of real steps (most first), so the samples with an r-th step are
    ranks 0..counts[r]-1, and the r-th steps are packed rows sum(counts[:r]) onwards in rank order.
    """

    batch: int
    order: Tensor  # (B,) the sample at each rank
    counts: list[int]  # samples with more than r real steps, for r = 0 .. longest - 1
    rank: Tensor  # (M,) each packed step's sample rank
    ordinal: Tensor  # (M,) r: its place among its sample's real steps
    sample: Tensor  # (M,) its sample in the window
    step: Tensor  # (M,) its step in the window

    @classmethod
    def of(cls, step_valid: Tensor) -> "PackedSteps":
        device = step_valid.device
        real = step_valid.sum(1)
        order = torch.sort(real, descending=True, stable=True).indices
        # Each ranked sample's real steps first, in window order.
        steps_first = torch.sort((~step_valid[order]).to(torch.uint8), dim=1, stable=True).indices
        counts = torch.bincount(real, minlength=step_valid.shape[1] + 1).flip(0).cumsum(0).flip(0)[1:]
        counts = [c for c in counts.tolist() if c > 0]
        repeats = torch.tensor(counts, dtype=torch.long, device=device)
        ordinal = torch.repeat_interleave(torch.arange(len(counts), device=device), repeats)
        rank = torch.cat([torch.arange(c, device=device) for c in counts]) if counts else ordinal
        return cls(batch=step_valid.shape[0], order=order, counts=counts, rank=rank, ordinal=ordinal,
                   sample=order[rank], step=steps_first[rank, ordinal])


class BlockCausalLayer(nn.Module):
    """Cross-attention to the instruction and all tokens of steps <= t, self-attention within step t, FFN."""

    def __init__(self, config: HiveformerConfig):
        super().__init__()
        dim = config.hidden_dim
        self.use_history = config.use_history
        self.cross_attention = MultiHeadAttention(dim, config.num_heads, config.attention_dropout)
        self.self_attention = MultiHeadAttention(dim, config.num_heads, config.attention_dropout)
        self.feedforward = nn.Sequential(
            nn.Linear(dim, config.feedforward_dim),
            nn.GELU(),
            Dropout(config.dropout),
            nn.Linear(config.feedforward_dim, dim),
        )
        self.norms = nn.ModuleList([nn.LayerNorm(dim) for _ in range(3)])
        self.dropout = Dropout(config.dropout)

    def forward(
        self,
        tokens: Tensor,
        instruction: Tensor,
        cross_allowed: Tensor | None,
        history: Tensor | None = None,
    ) -> Tensor:
        """tokens (B, T, N, D) -> (B, T, N, D); instruction (B, L, D); cross_allowed (B, 1, T*N, L + S' + T*N)
        or None (all allowed), where `history` (B, S', D) holds earlier tokens that are keys but not queries
        (none by default)."""
        batch, steps, per_step, dim = tokens.shape
        x = tokens.flatten(1, 2)  # (B, T*N, D)
        keys = [instruction, x] if history is None else [instruction, history, x]
        x = self.norms[0](x + self.dropout(self.cross_attention(x, torch.cat(keys, dim=1), cross_allowed)))
        return self._within_steps(x.view(batch * steps, per_step, dim)).view(batch, steps, per_step, dim)

    def forward_packed(self, x: Tensor, instruction: Tensor, instruction_mask: Tensor, packing: PackedSteps) -> Tensor:
        """The layer on the real steps of a window packed as `packing`: x (M, N, D) -> (M, N, D)."""
        attended = self.cross_attention.block_causal(x, instruction, instruction_mask, packing, self.use_history)
        return self._within_steps(self.norms[0](x + self.dropout(attended)))

    def _within_steps(self, x: Tensor) -> Tensor:
        """Self-attention within each step (the steps are separate sequences: no mask), then the FFN."""
        x = self.norms[1](x + self.dropout(self.self_attention(x, x)))
        return self.norms[2](x + self.dropout(self.feedforward(x)))


def block_causal_mask(
    step_valid: Tensor, instruction_mask: Tensor, per_step: int, use_history: bool, query_steps: slice
) -> Tensor | None:
    """Which keys each query token of the steps `query_steps` may attend to: (B, 1, Q*N, L + T*N) bool.

    The rollout's last layer uses it for the newest step; training runs the packed layers instead
    (`BlockCausalLayer.forward_packed`, the same values; its test compares the two on whole windows).

    Keys are the instruction tokens (L, `instruction_mask` (B, L)), then the N tokens of each of the T
    steps of the window: the query's own step and, with history, the earlier ones, unless padding
    (`step_valid` (B, T) False). None when every query may attend to every key, so that attention runs
    without a mask.
    """
    steps = step_valid.shape[1]
    only_last = range(steps)[query_steps] == range(steps - 1, steps)
    if use_history and only_last and bool(step_valid.all()) and bool(instruction_mask.all()):
        return None  # a rollout's newest step sees every key: skip building the mask
    step = torch.arange(steps, device=step_valid.device)
    query_step = step[query_steps]
    if use_history:
        allowed = step[None, :] <= query_step[:, None]  # (Q, T)
    else:
        allowed = step[None, :] == query_step[:, None]
    allowed = allowed[None] & step_valid[:, None, :]  # (B, Q, T)
    history = allowed.repeat_interleave(per_step, dim=1).repeat_interleave(per_step, dim=2)  # (B, QN, TN)
    instruction = instruction_mask[:, None, :].expand(-1, history.shape[1], -1)  # (B, Q*N, L)
    mask = torch.cat([instruction, history], dim=2).unsqueeze(1)
    return None if bool(mask.all()) else mask

