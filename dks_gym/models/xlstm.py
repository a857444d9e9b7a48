"""The xLSTM latent map: W_out mLSTM(W_in [z; s] + b_in) + b_out at context length one (Appendix A.3)."""

from __future__ import annotations

import torch
from torch import nn


def xlstm_block_stack(
    embedding_dim: int = 32, num_heads: int = 4, conv_kernel: int = 4, qkv_blocksize: int = 4
) -> nn.Module:
    """The reference ``xLSTMBlockStack``: one mLSTM block, no sLSTM, context length 1 (Appendix A.3)."""
    from xlstm import mLSTMBlockConfig, mLSTMLayerConfig, xLSTMBlockStack, xLSTMBlockStackConfig

    config = xLSTMBlockStackConfig(
        mlstm_block=mLSTMBlockConfig(
            mlstm=mLSTMLayerConfig(
                conv1d_kernel_size=conv_kernel, qkv_proj_blocksize=qkv_blocksize, num_heads=num_heads
            )
        ),
        slstm_at=[],
        context_length=1,
        num_blocks=1,
        embedding_dim=embedding_dim,
    )
    return xLSTMBlockStack(config)


def _one_step_guard(module: nn.Module, args: tuple) -> None:
    # With context_length 1 the stack's causal mask is 1x1 and broadcasts: a longer sequence would
    # silently let every step see future steps. The map is only defined one step at a time.
    x = args[0]
    if x.ndim != 3 or x.shape[1] != 1:
        raise ValueError(
            f"the xLSTM latent map is evaluated one step at a time (input (B, 1, D)), got shape {tuple(x.shape)}; "
            "call it once per step instead of on a sequence"
        )


class XLSTMTransition(nn.Module):
    """Gated one-step map on R^r: Linear(2r, 32) -> xLSTMBlockStack -> Linear(32, r).

    The recurrent state (C, n, m) is initialised afresh on every call and discarded, so the map is
    Markov in z (Appendix A.3). With xlstm 2.0.6 the stack has 8,968 parameters and the map 12,104 at
    r = 32; the paper's 43,104 is not reachable with this package version at the stated configuration.
    """

    def __init__(
        self,
        r: int,
        embedding_dim: int = 32,
        num_heads: int = 4,
        conv_kernel: int = 4,
        qkv_blocksize: int = 4,
    ) -> None:
        super().__init__()
        self.r = r
        self.proj_in = nn.Linear(2 * r, embedding_dim)  # W_in, b_in
        self.stack = xlstm_block_stack(embedding_dim, num_heads, conv_kernel, qkv_blocksize)
        self.stack.register_forward_pre_hook(_one_step_guard)
        self.proj_out = nn.Linear(embedding_dim, r)  # W_out, b_out

    def forward(self, z: torch.Tensor, s: torch.Tensor) -> torch.Tensor:
        """(B, r) latent states and (B, r) embeddings -> (B, r); sequences are refused."""
        if z.ndim != 2 or s.ndim != 2:
            raise ValueError(
                f"the xLSTM latent map takes one step at a time: z and s must be (B, r), got {tuple(z.shape)} "
                f"and {tuple(s.shape)}"
            )
        u = self.proj_in(torch.cat([z, s], dim=-1))[:, None, :]  # (B, 1, D): a sequence of length one
        return self.proj_out(self.stack(u)[:, 0, :])
