"""The decoder's exact predictive variance ``diag(G P G^T)`` (dks_gym.models.decoder_variance), each against
something independent:

* the whole Jacobian from torch's autodiff (``torch.autograd.functional.jacobian``) in float64 on tiny
  decoders of every shape the presets use (1D, 2D and 3D; upsampling and strided transposed convolutions;
  odd grids and edges), and after a weight changes (the precomputed stages follow it);
* the same from the GELU inputs the decode records (one forward pass for the field and its variance), and
  the field then bitwise the decode's;
* the formula it replaces, on the lite models in float32: ``r`` forward-mode Jacobian-vector products of the
  whole decoder (Koopman, MLP; pDMD's exact Jacobian times the factor: tests/test_pdmd.py);
* the fallback where the decoder has an activation the hand linearization does not know;
* the workspace kept between calls: the same numbers after calls of other sizes and from two threads at once.
"""

from __future__ import annotations

import concurrent.futures
import copy
import dataclasses

import pytest
import torch
from torch import nn

from dks_gym.assimilation import jacobian_variance
from dks_gym.assimilation.uncertainty import _jvp_variance
from dks_gym.dataset import Dataset
from dks_gym.filters.covariance import psd_sqrt
from dks_gym.models import BackboneSpec, benchmark_shape, build_model
from dks_gym.models.backbones import ConvDecoder
from dks_gym.models.decoder_variance import decoder_variance, supports_decoder_variance

R = 5
DECODERS = {  # benchmark (for ndim and channels), spec, grid
    "1d-upsample": ("burgers", BackboneSpec((2, 4, 8), (16,), 3, 1, False, "upsample"), (32,)),
    "1d-transpose": ("burgers", BackboneSpec((2, 4, 8), (16, 12), 5, 2, False, "transpose"), (24,)),
    "2d-upsample": ("cylinder", BackboneSpec((3, 4, 5), (16,), 5, 2, False, "upsample"), (16, 24)),
    "3d-transpose": ("sphere", BackboneSpec((2, 3, 4), (16,), 3, 1, True, "transpose"), (8, 16, 8)),
    "one-stage-no-hidden-layer": ("burgers", BackboneSpec((3,), (), 3, 1, False, "upsample"), (12,)),
}


def _tiny_decoder(name: str, seed: int = 0) -> ConvDecoder:
    benchmark, spec, grid = DECODERS[name]
    torch.manual_seed(seed)
    decoder = ConvDecoder(dataclasses.replace(benchmark_shape(benchmark), grid=grid), spec, R).double().eval()
    with torch.no_grad():
        for p in decoder.parameters():  # O(1) weights: the GELUs work in their curved part
            p.normal_(0.0, 0.5)
    return decoder


def _autodiff_variance(decoder: nn.Module, x: torch.Tensor, factor: torch.Tensor) -> torch.Tensor:
    """diag(J F F^T J^T) per element with J the whole Jacobian from torch's autodiff (one vectorized forward-mode
    pass per input coordinate: r of them, cheaper here than one reverse pass per output cell), (B, n_out)."""
    out = []
    for xb, fb in zip(x, factor):
        J = torch.autograd.functional.jacobian(lambda v: decoder(v[None])[0], xb, vectorize=True,
                                               strategy="forward-mode").reshape(-1, xb.shape[0])
        out.append((J @ fb).pow(2).sum(-1))
    return torch.stack(out).detach()  # the weights require grad; the reference is a number


@pytest.mark.parametrize("name", DECODERS)
def test_decoder_variance_equals_the_autodiff_jacobian(name: str) -> None:
    decoder = _tiny_decoder(name)
    assert supports_decoder_variance(decoder)
    g = torch.Generator().manual_seed(1)
    x = torch.randn(3, R, generator=g, dtype=torch.float64)
    factor = torch.randn(3, R, 4, generator=g, dtype=torch.float64)  # d = 4 columns: any factor, not square
    var = decoder_variance(decoder, x, factor)
    assert var.shape == (3, decoder.deconv[-1].out_channels, *DECODERS[name][2])
    reference = _autodiff_variance(decoder, x, factor)
    torch.testing.assert_close(var.flatten(1), reference, rtol=1e-12, atol=1e-12 * float(reference.max()))


@pytest.mark.parametrize("name", DECODERS)
def test_decoder_variance_from_the_decoders_own_pass_equals_the_autodiff_jacobian(name: str) -> None:
    """The GELU inputs recorded by the decode (``decoder(x, preactivations)``) in place of a primal pass."""
    decoder = _tiny_decoder(name)
    g = torch.Generator().manual_seed(4)
    x = torch.randn(3, R, generator=g, dtype=torch.float64)
    factor = torch.randn(3, R, 4, generator=g, dtype=torch.float64)
    preactivations: list[torch.Tensor] = []
    out = decoder(x, preactivations)
    assert torch.equal(out, decoder(x)) and len(preactivations) == len(decoder.deconv) - 1
    var = decoder_variance(decoder, x, factor, preactivations)
    reference = _autodiff_variance(decoder, x, factor)
    torch.testing.assert_close(var.flatten(1), reference, rtol=1e-12, atol=1e-12 * float(reference.max()))
    if preactivations:
        with pytest.raises(ValueError, match="preactivations must be what decoder"):
            decoder_variance(decoder, x[:2], factor[:2], preactivations)


def test_decode_with_variance_is_decode_and_its_variance(burgers_small) -> None:
    """One forward pass for both: the field bitwise decode()'s (300 rows: the decode splits them in blocks),
    the variance the separate call's to float32 round-off."""
    model = build_model("burgers", "koopman", r=8, preset="lite", dataset=Dataset(burgers_small), seed=0)
    g = torch.Generator().manual_seed(5)
    z, mu = torch.randn(300, 8, generator=g), torch.rand(300, generator=g)
    factor = torch.randn(300, 8, 8, generator=g) / 3
    with torch.no_grad():
        field, var = model.decode_with_variance(z, mu, factor)
        assert torch.equal(field, model.decode(z, mu))
        alone = model.decoder_variance(z, mu, factor)
    scale = alone.amax(dim=(1, 2), keepdim=True)
    assert float(((var - alone).abs() / scale).max()) < 1e-5


def test_decoder_variance_follows_a_weight_change() -> None:
    decoder = _tiny_decoder("1d-upsample")
    x, factor = torch.randn(2, R, dtype=torch.float64), torch.randn(2, R, R, dtype=torch.float64)
    before = decoder_variance(decoder, x, factor)  # precomputes (and caches) the stages
    with torch.no_grad():
        decoder.deconv[1].weight.mul_(1.5)
        decoder.fc[-1].bias.add_(0.3)
    after = decoder_variance(decoder, x, factor)
    assert (after - before).abs().max() > 1e-2 * before.abs().max()
    torch.testing.assert_close(after.flatten(1), _autodiff_variance(decoder, x, factor), rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize("kind", ["koopman", "mlp"])  # pDMD: tests/test_pdmd.py
def test_predictive_variance_equals_the_jacobian_vector_products_in_float32(burgers_small, kind: str) -> None:
    model = build_model("burgers", kind, r=8, preset="lite", dataset=Dataset(burgers_small), seed=0)
    g = torch.Generator().manual_seed(2)
    z = torch.randn(4, 8, generator=g)
    mu = torch.tensor([0.01, 0.1, 0.5, 1.0])
    M = torch.randn(4, 8, 8, generator=g)
    P = M @ M.mT / 8
    var = jacobian_variance(model, z, mu, P)
    reference = _jvp_variance(model, z, mu, psd_sqrt(P))
    assert var.shape == reference.shape == (4, 1, 1024)
    # float32 round-off of sums over the 8 columns, relative to each element's largest cell
    scale = reference.amax(dim=-1, keepdim=True)
    assert float(((var - reference).abs() / scale).max()) < 1e-5


def test_an_unknown_activation_falls_back_to_jacobian_vector_products() -> None:
    model = build_model("burgers", "koopman", r=4, preset="lite", seed=0).double()
    assert model.decoder_variance(torch.zeros(1, 4, dtype=torch.float64), torch.tensor([0.1]),
                                  torch.eye(4, dtype=torch.float64)[None]) is not None
    tanh_gelu = copy.deepcopy(model)
    tanh_gelu.decoder.act = nn.GELU(approximate="tanh")
    assert not supports_decoder_variance(tanh_gelu.decoder)
    z, mu = torch.randn(2, 4, dtype=torch.float64), torch.tensor([0.1, 0.9], dtype=torch.float64)
    P = torch.eye(4, dtype=torch.float64).expand(2, 4, 4) * 0.1
    assert tanh_gelu.decoder_variance(z, mu, psd_sqrt(P)) is None
    var = jacobian_variance(tanh_gelu, z, mu, P)
    torch.testing.assert_close(var, _jvp_variance(tanh_gelu, z, mu, psd_sqrt(P)), rtol=0, atol=0)
    with pytest.raises(TypeError, match="exact GELU"):
        decoder_variance(tanh_gelu.decoder, z, psd_sqrt(P))


def test_the_kept_workspace_changes_no_result() -> None:
    """The padded fields are kept from call to call (per thread, weight set and column count): a result
    stays as returned after later calls of other sizes, and threads calling at once do not share fields."""
    decoder = _tiny_decoder("1d-upsample")
    g = torch.Generator().manual_seed(3)
    cases = [(torch.randn(b, R, generator=g, dtype=torch.float64),
              torch.randn(b, R, d, generator=g, dtype=torch.float64)) for b, d in ((3, 4), (2, 4), (3, 2), (5, 4))]
    results = [decoder_variance(decoder, x, f) for x, f in cases]
    for (x, f), var in zip(cases, results):  # each checked only after every call has run
        torch.testing.assert_close(var.flatten(1), _autodiff_variance(decoder, x, f), rtol=1e-12, atol=1e-12)
    # Two threads at once, on a decoder big enough for torch's operators (which release the GIL) to overlap.
    lite = build_model("burgers", "koopman", r=8, preset="lite", seed=0).decoder
    inputs = [(torch.randn(64, 8, generator=g), torch.randn(64, 8, 8, generator=g)) for _ in range(2)]
    alone = [decoder_variance(lite, *case) for case in inputs]
    with concurrent.futures.ThreadPoolExecutor(2) as pool:
        together = list(pool.map(lambda case: [decoder_variance(lite, *case) for _ in range(10)], inputs))
    for runs, var in zip(together, alone):
        for run in runs:
            torch.testing.assert_close(run, var, rtol=0, atol=0)


def test_bad_shapes_raise_clear_errors() -> None:
    decoder = _tiny_decoder("1d-upsample")
    with pytest.raises(ValueError, match=r"factor \(B, r, d\)"):
        decoder_variance(decoder, torch.zeros(2, R, dtype=torch.float64), torch.zeros(2, R + 1, 3, dtype=torch.float64))


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_decoder_variance_on_cuda_matches_cpu() -> None:
    model = build_model("burgers", "koopman", r=8, preset="lite", seed=0).double()
    z, mu = torch.randn(5, 8, dtype=torch.float64), torch.linspace(0.01, 1.0, 5, dtype=torch.float64)
    M = torch.randn(5, 8, 8, dtype=torch.float64)
    P = M @ M.mT / 8
    cpu = jacobian_variance(model, z, mu, P)
    field, shared = model.decode_with_variance(z, mu, psd_sqrt(P))
    cuda = jacobian_variance(model.to("cuda"), z.cuda(), mu.cuda(), P.cuda())
    torch.testing.assert_close(cuda.cpu(), cpu, rtol=1e-10, atol=1e-14)
    field_cuda, shared_cuda = model.decode_with_variance(z.cuda(), mu.cuda(), psd_sqrt(P).cuda())
    torch.testing.assert_close(field_cuda.cpu(), field, rtol=1e-10, atol=1e-12)
    torch.testing.assert_close(shared_cuda.cpu(), shared, rtol=1e-10, atol=1e-14)
