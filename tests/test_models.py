"""Neural latent models: paper parameter counts, Koopman structure, Jacobians, xLSTM one-step guard, I/O."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.linalg
import torch

from dks_gym.models import (
    BENCHMARK_SHAPES,
    PAPER_LATENT_PARAM_COUNTS,
    PAPER_PARAM_COUNTS,
    ParameterEmbedding,
    build_model,
    count_parameters,
)
from dks_gym.models.training import adam

BENCHMARKS = tuple(BENCHMARK_SHAPES)


def _mu_grid(benchmark: str, n: int) -> torch.Tensor:
    low, high = BENCHMARK_SHAPES[benchmark].param_range
    return torch.linspace(low, high, n, dtype=torch.float64)


def _lite(benchmark: str, kind: str, r: int = 8, seed: int = 0, **kwargs) -> torch.nn.Module:
    shape = BENCHMARK_SHAPES[benchmark]
    if shape.has_cell_type and "cell_type" not in kwargs:
        kwargs["cell_type"] = np.random.default_rng(seed).integers(0, 5, size=shape.grid).astype(np.int8)
    return build_model(benchmark, kind, r=r, preset="lite", seed=seed, **kwargs)


# Parameter counts (paper table tab:ld32_param_counts) -----------------------------------------------
def test_embedding_has_paper_parameter_count():
    # Linear(1, 32) + 4 Linear(32, 32) = 64 + 4 * 1056
    assert count_parameters(ParameterEmbedding(32, (0.0, 1.0))) == 4_288


@pytest.mark.parametrize("benchmark", BENCHMARKS)
def test_paper_preset_parameter_counts_match_paper_table(benchmark):
    encoder, decoder = PAPER_PARAM_COUNTS[benchmark]
    # Literal copy of the paper's table, independent of the presets module.
    assert (encoder, decoder) == {
        "burgers": (2_243_504, 2_243_249),
        "cylinder": (21_031_264, 21_056_003),
        "dambreak": (21_037_664, 21_062_405),
        "sphere": (38_247_008, 38_274_949),
    }[benchmark]
    for kind, latent in (("koopman", 43_296), ("mlp", 43_607)):
        assert PAPER_LATENT_PARAM_COUNTS[kind] == latent
        with torch.device("meta"):  # no memory for the 38M-parameter sphere backbone
            model = build_model(benchmark, kind, r=32, preset="paper")
        counts = model.param_counts()
        assert counts == {"encoder": encoder, "decoder": decoder, "latent_map": latent}
        assert count_parameters(model) == encoder + decoder + latent  # nothing outside the three parts


def test_backbone_channels_follow_the_paper_tables():
    # (encoder input, decoder output) channels: Burgers 1/1, cylinder 4/3, dambreak 6/5, sphere 5/5.
    expected = {"burgers": (1, 1), "cylinder": (4, 3), "dambreak": (6, 5), "sphere": (5, 5)}
    for name, (c_in, c_out) in expected.items():
        shape = BENCHMARK_SHAPES[name]
        assert (shape.in_channels, shape.out_channels) == (c_in, c_out)


def test_xlstm_parameter_count_is_what_the_installed_package_yields():
    from xlstm import mLSTMBlockConfig, mLSTMLayerConfig, xLSTMBlockStack, xLSTMBlockStackConfig

    stack = xLSTMBlockStack(
        xLSTMBlockStackConfig(
            mlstm_block=mLSTMBlockConfig(
                mlstm=mLSTMLayerConfig(conv1d_kernel_size=4, qkv_proj_blocksize=4, num_heads=4)
            ),
            slstm_at=[],
            context_length=1,
            num_blocks=1,
            embedding_dim=32,
        )
    )
    r = 32
    expected = count_parameters(stack) + (2 * r * 32 + 32) + (32 * r + r)  # + W_in, b_in, W_out, b_out
    with torch.device("meta"):
        model = build_model("burgers", "xlstm", r=r)
    assert model.param_counts()["latent_map"] == expected
    assert model.param_counts()["encoder"] == PAPER_PARAM_COUNTS["burgers"][0]
    from importlib.metadata import version

    if version("xlstm") == "2.0.6":  # the version the README's 12,104 was counted with
        assert expected == 12_104


# Koopman operator (Eqs. 7-9) ---------------------------------------------------------------------------
@pytest.mark.parametrize("benchmark", ["burgers", "cylinder"])  # dt = 0.005 (near-isometric) and 0.5
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_koopman_operator_is_non_expansive_for_random_weights(benchmark, seed):
    torch.manual_seed(seed)
    model = build_model(benchmark, "koopman", r=16, preset="lite", seed=seed)
    with torch.no_grad():
        for p in model.latent_map.parameters():  # far from the default initialization
            p.mul_(1 + 4 * torch.rand(()))
            p.add_(torch.randn_like(p))
    low, high = BENCHMARK_SHAPES[benchmark].param_range
    mu = torch.cat([_mu_grid(benchmark, 200), torch.tensor([low - 10 * high, 0.0, 10 * high], dtype=torch.float64)])
    with torch.no_grad():
        k = model.koopman_operator(mu)
    norms = torch.linalg.matrix_norm(k.double(), ord=2)
    assert norms.max() <= 1 + 1e-6
    assert norms.min() < 1  # the dissipative term acts


def test_koopman_operator_equals_expm_of_skew_minus_diagonal_generator():
    model = _lite("burgers", "koopman", r=12)
    mu = _mu_grid("burgers", 7)
    with torch.no_grad():
        k = model.koopman_operator(mu).double().numpy()
        s = model.embed_param(mu)
        q = model.latent_map.q_net(s).double().numpy().reshape(-1, 12, 12)
        d = model.latent_map.d_net(s).double().numpy()
    for i in range(len(mu)):
        a = q[i] - q[i].T - np.diag(d[i] ** 2)
        np.testing.assert_allclose(k[i], scipy.linalg.expm(a * 0.005), atol=2e-7)
    assert model.dt == 0.005  # the Burgers latent step of the paper's table


@pytest.mark.parametrize("scale", [0.3, 25.0])  # the 1-norms of A dt of the trained lite Burgers and cylinder models
def test_taylor_matrix_exp_is_as_accurate_as_float32_matrix_exp(scale):
    """The training formulation of K (float32 scaling and squaring of a Taylor series) against
    torch.linalg.matrix_exp in float64, value and gradient, measured beside float32's own matrix_exp."""
    from dks_gym.models.koopman import dissipative_generator, taylor_matrix_exp

    gen = torch.Generator().manual_seed(0)
    a = dissipative_generator(torch.randn(8, 16, 16, generator=gen, dtype=torch.float64),
                              torch.rand(8, 16, generator=gen, dtype=torch.float64))
    a = a * scale / float(a.abs().sum(-2).amax())
    weights = torch.randn(8, 16, 16, generator=gen, dtype=torch.float64)

    def value_and_grad(fn, dtype):
        x = a.to(dtype).requires_grad_(True)
        k = fn(x)
        (grad,) = torch.autograd.grad((k * weights.to(dtype)).sum(), x)
        return k.detach().double(), grad.double()

    k_ref, g_ref = value_and_grad(torch.linalg.matrix_exp, torch.float64)
    k_32, g_32 = value_and_grad(torch.linalg.matrix_exp, torch.float32)
    k_taylor, g_taylor = value_and_grad(taylor_matrix_exp, torch.float32)
    assert (k_taylor - k_ref).abs().max() <= 2 * (k_32 - k_ref).abs().max()
    assert (g_taylor - g_ref).abs().max() <= 2 * (g_32 - g_ref).abs().max()
    torch.testing.assert_close(taylor_matrix_exp(a), k_ref, rtol=0, atol=1e-13)  # float64: to its round-off


def test_training_mode_koopman_operator_equals_the_float64_one():
    model = _lite("cylinder", "koopman", r=8)  # dt = 0.5: several squarings
    mu = _mu_grid("cylinder", 5)
    with torch.no_grad():
        k_eval = model.koopman_operator(mu)
        model.train()
        k_train = model.koopman_operator(mu)
    assert k_train is not k_eval  # not taken from the cache of the other mode
    torch.testing.assert_close(k_train, k_eval, rtol=0, atol=2e-6)


def test_koopman_cache_follows_parameter_updates():
    model = _lite("burgers", "koopman", r=8)
    mu = _mu_grid("burgers", 4)
    with torch.no_grad():
        k1 = model.koopman_operator(mu)
        assert model.koopman_operator(mu) is k1  # cached
    opt = adam(model, lr=0.1)  # the training runs' optimizer: its update must be seen by the cache
    model.koopman_operator(mu).sum().backward()  # grad enabled: computed afresh, differentiable
    opt.step()
    with torch.no_grad():
        k2 = model.koopman_operator(mu)
        fresh = model.latent_map.operator(model.embed_param(mu))
    assert not torch.allclose(k1, k2)
    torch.testing.assert_close(k2, fresh)


# Jacobians ---------------------------------------------------------------------------------------------
@pytest.mark.parametrize("kind", ["koopman", "mlp", "xlstm"])
def test_forecast_jacobian_equals_autograd_jacobian(kind):
    model = _lite("burgers", kind, r=8)
    torch.manual_seed(3)
    z = torch.randn(5, 8)
    mu = _mu_grid("burgers", 5)
    with torch.no_grad():  # filters call it without gradient recording
        jac = model.forecast_jacobian(z, mu)
    assert jac.shape == (5, 8, 8)
    for i in range(5):
        ref = torch.autograd.functional.jacobian(lambda v: model.forecast(v[None], mu[i : i + 1])[0], z[i])
        torch.testing.assert_close(jac[i], ref, atol=1e-5, rtol=1e-5)
    if kind == "koopman":
        torch.testing.assert_close(jac, model.koopman_operator(mu).detach())
    else:
        assert not torch.allclose(jac[0], jac[1])  # state dependent


def test_decoder_jacobian_equals_central_differences_of_the_decoder():
    model = _lite("burgers", "mlp", r=4).double()
    torch.manual_seed(4)
    z = torch.randn(2, 4, dtype=torch.float64)
    mu = _mu_grid("burgers", 2).double()
    G = model.decoder_jacobian(z, mu)
    assert G.shape == (2, 1, 1024, 4)
    h = 1e-6
    for i in range(4):
        dz = torch.zeros_like(z)
        dz[:, i] = h
        with torch.no_grad():
            fd = (model.decode(z + dz, mu) - model.decode(z - dz, mu)).flatten(2) / (2 * h)
        torch.testing.assert_close(G[..., i], fd, rtol=1e-6, atol=1e-8)


@pytest.mark.parametrize(("preset", "r"), [("lite", 4), ("paper", 4), ("lite", 20)])
def test_sensor_local_jacobian_equals_central_differences_of_the_whole_decoder(preset, r):
    """The filters' observation Jacobian decodes only each sensor's window of the bottleneck; it must equal the
    derivative of the whole decode at the sensors, at the grid's edges (where the window is clamped) too.
    Through the dense layers it carries the r columns forward (16 sensors > r = 4) or the 16 rows back (r = 20)."""
    model = build_model("burgers", "mlp", r=r, preset=preset, seed=0).double()
    assert model.decoder.window() == (5,)  # 2 * 2 + 1 of the 128 bottleneck cells
    torch.manual_seed(5)
    z = torch.randn(3, r, dtype=torch.float64)
    mu = _mu_grid("burgers", 3)
    rng = np.random.default_rng(0)
    sensors = np.stack([np.r_[0, 1, 7, 8, 1015, 1022, 1023, rng.choice(1024, 9, replace=False)] for _ in range(3)])
    jacobian = model.filter_observe_jacobian(mu, lambda n: sensors.repeat(n // 3, axis=0), "u")
    h_local, J = jacobian(z)
    assert J.shape == (3, 16, r)
    with torch.no_grad():
        torch.testing.assert_close(h_local, model.decode(z, mu).flatten(2)[:, 0].gather(1, torch.as_tensor(sensors)),
                                   rtol=1e-12, atol=1e-12)
    h = 1e-6
    for i in range(r):
        dz = torch.zeros_like(z)
        dz[:, i] = h
        with torch.no_grad():
            fd = (model.decode(z + dz, mu) - model.decode(z - dz, mu)).flatten(2)[:, 0] / (2 * h)
        torch.testing.assert_close(J[..., i], fd.gather(1, torch.as_tensor(sensors)), rtol=1e-6, atol=1e-9)
    # The values it decodes on the windows are the whole decode's.
    x = z + model.embed_param(mu)
    values, _ = model.decoder.sensor_jacobian(x, torch.as_tensor(sensors), 0)
    with torch.no_grad():
        whole = model.decoder(x)[:, 0].gather(1, torch.as_tensor(sensors))
    torch.testing.assert_close(values, whole, rtol=1e-12, atol=1e-12)


def test_sensor_window_narrower_than_the_receptive_field_is_wrong(monkeypatch):
    """The check above can fail: one bottleneck cell too few and interior sensors read cropped windows."""
    model = build_model("burgers", "mlp", r=4, preset="lite", seed=0).double()
    cells = torch.tensor([[300, 517, 700]])
    x = torch.randn(1, 4, dtype=torch.float64)
    _, right = model.decoder.sensor_jacobian(x, cells, 0)
    monkeypatch.setattr(type(model.decoder), "receptive_radius", property(lambda self: 1))
    _, wrong = model.decoder.sensor_jacobian(x, cells, 0)
    assert not torch.allclose(right, wrong, rtol=1e-6, atol=0)


def test_sensor_local_jacobian_is_used_only_where_a_window_saves_work():
    assert build_model("burgers", "koopman", preset="lite").decoder.window() == (5,)
    for benchmark in ("cylinder", "dambreak"):  # 7 x 7 of an 8 x 8 bottleneck: one whole decode per sensor is cheaper
        model = _lite(benchmark, "koopman")
        assert model.decoder.window() is None
        assert model.filter_observe_jacobian(torch.ones(1), lambda n: np.zeros((n, 2), np.int64),
                                             model.shape.channels[0]) is None
    assert _lite("sphere", "koopman").decoder.window() == (3, 3, 3)


@pytest.mark.parametrize("benchmark, preset", [("burgers", "lite"), ("burgers", "paper"), ("cylinder", "lite"),
                                               ("sphere", "lite")])
def test_decoder_at_cells_equals_the_whole_decode(benchmark, preset):
    """The decoder at chosen cells from only the cells each reads (one window per cell, cropped stage by stage)
    equals the whole decode there in float64 to round-off: at every cell of the 1D grid (both edges, where the
    windows are clamped) and at the 2D and 3D grids' corners, edges and cells inside, with one layout for every
    row and one per row (16 cells of one layout: the crops folded into per-cell matrices)."""
    from dataclasses import replace

    from dks_gym.models.backbones import ConvDecoder
    from dks_gym.models.presets import backbone_spec

    shape, spec = BENCHMARK_SHAPES[benchmark], backbone_spec(benchmark, preset)
    if shape.ndim > 1:  # narrower layers (the same kernels, paddings and stages): float64 convolutions are slow
        spec = replace(spec, conv_channels=(2,) * len(spec.conv_channels), fc_widths=(16,))
    decoder = ConvDecoder(shape, spec, 4).double().eval()
    torch.manual_seed(6)
    x = torch.randn(2, 4, dtype=torch.float64)
    n_cells = int(np.prod(shape.grid))
    if shape.ndim == 1:
        cells = np.arange(n_cells)
    else:  # the corners and edges of the grid, and cells inside
        edges = [0, 1, 2, shape.grid[0] - 2, shape.grid[0] - 1]
        corners = np.ravel_multi_index(np.stack(np.meshgrid(*[edges] * shape.ndim)).reshape(shape.ndim, -1), shape.grid)
        cells = np.r_[corners, np.random.default_rng(0).choice(n_cells, 10, replace=False)]
    with torch.no_grad():
        whole = decoder(x).flatten(2)
        for channel in (0, whole.shape[1] - 1):
            shared = torch.as_tensor(cells).expand(2, -1)  # one layout
            per_row = torch.as_tensor(np.stack([cells, cells[::-1].copy()]))  # a layout per row
            few = torch.as_tensor(cells[:: len(cells) // 16][:16]).expand(2, -1)
            for layout in (shared, per_row, few):
                torch.testing.assert_close(decoder.at_cells(x, layout, channel), whole[:, channel].gather(1, layout),
                                           rtol=1e-12, atol=1e-12)
        # the folded products of a layout are kept per layout and weights: new weights, new products
        decoder.fc[-1].weight.mul_(-2.0)
        decoder.deconv[-1].bias.add_(1.0)
        torch.testing.assert_close(decoder.at_cells(x, few, 0), decoder(x).flatten(2)[:, 0].gather(1, few),
                                   rtol=1e-12, atol=1e-12)


def test_observe_reads_per_row_layouts_as_the_whole_decode():
    """``observe`` with one layout per row (how the filters call it) equals the decoded fields at those cells: the
    Burgers model reads them from their windows, the cylinder model decodes the whole field."""
    for benchmark in ("burgers", "cylinder"):
        model = _lite(benchmark, "koopman", r=4).double()
        torch.manual_seed(7)
        z, mu = torch.randn(3, 4, dtype=torch.float64), _mu_grid(benchmark, 3)
        n_cells = int(np.prod(model.grid))
        rows = np.stack([np.random.default_rng(i).choice(n_cells, 6, replace=False) for i in range(3)])
        with torch.no_grad():
            fields = model.decode(z, mu).flatten(2)[:, -1]
            torch.testing.assert_close(model.observe(z, mu, rows, model.n_fields - 1),
                                       fields.gather(1, torch.as_tensor(rows)), rtol=1e-12, atol=1e-12)
            torch.testing.assert_close(model.observe(z, mu, rows[0], model.n_fields - 1), fields[:, rows[0]],
                                       rtol=1e-12, atol=1e-12)
    with pytest.raises(ValueError, match="one such layout per row"):
        model.observe(z, mu, rows[:2], 0)


def test_sphere_sensor_local_jacobian_equals_autodiff_through_the_whole_decoder():
    from dks_gym.filters.jacobians import value_and_jacobian

    model = _lite("sphere", "mlp", r=4)
    n_cells = int(np.prod(model.grid))
    sensors = np.array([[0, 1, 64 * 64 * 30 + 64 * 17 + 40, n_cells - 1]])  # two corners, the interior, an edge
    rows = lambda n: sensors.repeat(n, axis=0)  # noqa: E731
    mu = _mu_grid("sphere", 1).float()
    z = torch.randn(1, 4)

    def observe(zz: torch.Tensor) -> torch.Tensor:
        return model.decode(zz, mu).flatten(2)[:, 0].gather(1, torch.as_tensor(rows(zz.shape[0])))

    _, reference = value_and_jacobian(observe, z)
    _, local = model.filter_observe_jacobian(mu, rows, model.shape.channels[0])(z)
    torch.testing.assert_close(local, reference, rtol=1e-5, atol=1e-7 * float(reference.abs().max()))


@pytest.mark.parametrize("benchmark", BENCHMARKS)
def test_decoder_equals_torch_conv_transpose(benchmark):
    """The decoder runs blocks of rows and stride-1 transposed convolutions as plain ones (in training, on the CPU,
    in channels-last layout); its output, in and out of training, and its weight gradients must be those of
    torch's ConvTranspose on the whole batch to round-off."""
    decoder = _lite(benchmark, "mlp").decoder
    rows = 2 + (1 << 17) // int(np.prod(decoder.bottleneck[1:]) * 2 ** (len(decoder.deconv) * decoder.ndim))
    h = torch.randn(rows, *decoder.bottleneck)  # more rows than one block holds
    with torch.no_grad():
        reference = decoder.reference_convolve(h)
        torch.testing.assert_close(decoder.eval().convolve(h), reference, rtol=1e-5, atol=1e-6)
    decoder.train()
    outputs, grads = [], []
    for convolve in (decoder.convolve, decoder.reference_convolve):
        out = convolve(h[:4])
        outputs.append(out.detach())
        grads.append(torch.autograd.grad((out * out).sum(), list(decoder.deconv.parameters())))
    torch.testing.assert_close(outputs[0], outputs[1], rtol=1e-5, atol=1e-6)
    for fast, reference in zip(*grads):
        torch.testing.assert_close(fast, reference, rtol=1e-4, atol=1e-5 * float(reference.abs().max()))


@pytest.mark.parametrize("benchmark", BENCHMARKS)
def test_training_mode_encoder_equals_the_eval_one(benchmark):
    """In training on the CPU the encoder convolves in channels-last layout (1D maps as height-1 2D maps):
    output and weight gradients must be those of the eval-mode encoder (the layers as torch runs them)."""
    encoder = _lite(benchmark, "mlp").encoder.backbone
    x = torch.randn(3, encoder.conv[0].in_channels, *BENCHMARK_SHAPES[benchmark].grid)
    outputs, grads = [], []
    for training in (True, False):
        encoder.train(training)
        out = encoder(x)
        outputs.append(out.detach())
        grads.append(torch.autograd.grad((out * out).sum(), list(encoder.conv.parameters())))
    torch.testing.assert_close(outputs[0], outputs[1], rtol=1e-5, atol=1e-6)
    for fast, reference in zip(*grads):
        torch.testing.assert_close(fast, reference, rtol=1e-4, atol=1e-5 * float(reference.abs().max()))


# xLSTM one-step evaluation -------------------------------------------------------------------------------
def test_xlstm_refuses_sequences():
    model = _lite("burgers", "xlstm", r=8)
    z, s = torch.randn(3, 4, 8), torch.randn(3, 4, 8)
    with pytest.raises(ValueError, match="one step"):
        model.latent_map(z, s)
    with pytest.raises(ValueError, match="one step"):
        model.latent_map.stack(torch.randn(3, 2, 32))  # the stack itself is guarded too


def test_xlstm_map_is_one_recurrent_step_from_a_fresh_state():
    model = _lite("burgers", "xlstm", r=8)
    z, mu = torch.randn(4, 8), _mu_grid("burgers", 4)
    u = model.latent_map.proj_in(torch.cat([z, model.embed_param(mu)], dim=-1))[:, None]
    y_step, _ = model.latent_map.stack.step(u, state=None)  # the package's recurrent form, zero state
    expected = model.latent_map.proj_out(y_step[:, 0])
    torch.testing.assert_close(model.forecast(z, mu), expected, atol=1e-5, rtol=1e-5)


# Encode / decode ------------------------------------------------------------------------------------------
@pytest.mark.parametrize("benchmark", BENCHMARKS)
def test_lite_encode_decode_shapes_round_trip(benchmark):
    shape = BENCHMARK_SHAPES[benchmark]
    model = _lite(benchmark, "koopman", r=6)
    x = torch.randn(2, shape.n_fields, *shape.grid)
    mu = _mu_grid(benchmark, 2)
    with torch.no_grad():
        z = model.encode(x, mu)
        assert z.shape == (2, 6)
        assert model.decode(z, mu).shape == x.shape
        assert model.forecast(z, mu).shape == (2, 6)
        out = model.decode_normalized(z, mu)
    assert out.shape == (2, shape.out_channels, *shape.grid)
    assert model.encoder_input(x).shape[1] == shape.in_channels


def test_normalization_is_inside_encode_and_decode():
    mean, std = np.array([0.3, -1.0, 2.0]), np.array([2.0, 0.5, 4.0])
    ct = np.random.default_rng(0).integers(0, 5, size=(64, 64))
    scaled = build_model("cylinder", "mlp", r=4, preset="lite", stats_mean=mean, stats_std=std, cell_type=ct)
    plain = build_model("cylinder", "mlp", r=4, preset="lite", cell_type=ct)  # same seed, identity stats
    x = torch.randn(2, 3, 64, 64) * 3
    mu = _mu_grid("cylinder", 2)
    m_ = torch.tensor(mean, dtype=torch.float32)[:, None, None]
    s_ = torch.tensor(std, dtype=torch.float32)[:, None, None]
    with torch.no_grad():
        torch.testing.assert_close(scaled.encode(x, mu), plain.encode((x - m_) / s_, mu))
        z = torch.randn(2, 4)
        torch.testing.assert_close(scaled.decode(z, mu), plain.decode(z, mu) * s_ + m_)
        last = scaled.decoder.deconv[-1]
        last.weight.zero_()
        last.bias.zero_()
        torch.testing.assert_close(scaled.decode(z, mu), m_.expand(2, 3, 64, 64).contiguous())


def test_sphere_decoder_reconstructs_cell_type_but_decode_drops_it():
    ct = np.random.default_rng(1).integers(0, 5, size=(64, 64, 64))
    model = _lite("sphere", "mlp", r=4, cell_type=ct)
    x = torch.randn(1, 4, 64, 64, 64)
    target = model.reconstruction_target(x)
    assert target.shape == (1, 5, 64, 64, 64)
    np.testing.assert_array_equal(target[0, 4].numpy(), ct.astype(np.float32))
    with torch.no_grad():
        assert model.decode(torch.zeros(1, 4), 100.0).shape == (1, 4, 64, 64, 64)
    cyl = _lite("cylinder", "mlp", r=4)
    assert cyl.reconstruction_target(torch.randn(1, 3, 64, 64)).shape == (1, 3, 64, 64)


def test_observe_samples_the_decoded_channel():
    model = _lite("dambreak", "koopman", r=4)
    sensors = np.ravel_multi_index((np.array([0, 10, 63]), np.array([5, 20, 63])), (64, 64))
    z, mu = torch.randn(3, 4), _mu_grid("dambreak", 3)
    with torch.no_grad():
        y = model.observe(z, mu, sensors, channel=3)
        full = model.decode(z, mu)
        torch.testing.assert_close(model.observe(z, mu, sensors, channel="p"), y)  # channel 3 is p
    torch.testing.assert_close(y, full[:, 3, [0, 10, 63], [5, 20, 63]])


def test_bad_inputs_raise_clear_errors():
    model = _lite("cylinder", "koopman", r=4)
    with pytest.raises(ValueError, match=r"shape \(B, 3, 64, 64\)"):
        model.encode(torch.randn(3, 64, 64), 100.0)
    with pytest.raises(ValueError, match="mu must be"):
        model.encode(torch.randn(2, 3, 64, 64), torch.ones(3))
    with pytest.raises(ValueError, match=r"\(B, 4\)"):
        model.forecast(torch.randn(2, 5), 100.0)
    no_ct = build_model("cylinder", "koopman", r=4, preset="lite")
    with pytest.raises(RuntimeError, match="cell_type"):
        no_ct.encode(torch.randn(1, 3, 64, 64), 100.0)
    with pytest.raises(ValueError, match="unknown model"):
        build_model("cylinder", "lstm")
    with pytest.raises(ValueError, match="unknown benchmark"):
        build_model("channel", "koopman")


def test_seeded_construction_is_reproducible_and_leaves_global_rng_alone():
    torch.manual_seed(123)
    before = torch.rand(1)
    torch.manual_seed(123)
    a = build_model("burgers", "mlp", r=4, preset="lite", seed=7)
    after = torch.rand(1)
    b = build_model("burgers", "mlp", r=4, preset="lite", seed=7)
    assert torch.equal(before, after)
    for pa, pb in zip(a.parameters(), b.parameters()):
        assert torch.equal(pa, pb)


def test_rollout_repeats_forecast():
    model = _lite("burgers", "mlp", r=4)
    z0, mu = torch.randn(2, 4), _mu_grid("burgers", 2)
    with torch.no_grad():
        traj = model.rollout(z0, mu, 3)
        z = z0
        for k in range(3):
            z = model.forecast(z, mu)
        torch.testing.assert_close(traj[:, 3], z)
    assert traj.shape == (2, 4, 4)


@pytest.mark.parametrize("kind", ["koopman", "mlp", "xlstm"])
def test_float64_inputs_run_through_a_float32_model(kind):
    model = _lite("burgers", kind, r=4)
    z, mu = torch.randn(2, 4, dtype=torch.float64), _mu_grid("burgers", 2)
    with torch.no_grad():
        out = (model.forecast(z, mu), model.forecast_jacobian(z, mu), model.decode(z, mu))
        torch.testing.assert_close(out[0], model.forecast(z.float(), mu).double())
    assert all(t.dtype == torch.float64 for t in out)
    assert model.encode(torch.randn(2, 1, 1024, dtype=torch.float64), mu).dtype == torch.float64


@pytest.mark.parametrize("benchmark", ["burgers", "cylinder"])
def test_encoder_adds_the_parameter_embedding_as_a_residual(benchmark):
    """z = E_phi(x) + e(mu) (Eq. 6): the backbone never sees mu, so changing mu shifts z by e(mu') - e(mu)."""
    from dks_gym.benchmarks import get_benchmark

    bench = get_benchmark(benchmark)
    kwargs = {"cell_type": bench.cell_type()} if bench.ndim > 1 else {}
    model = build_model(benchmark, "koopman", r=8, preset="lite", seed=0, **kwargs).double()
    x = torch.randn(3, len(bench.channels), *bench.grid, dtype=torch.float64)
    lo, hi = bench.param_range
    mu = torch.tensor([lo, (lo + hi) / 2, hi], dtype=torch.float64)
    mu2 = torch.tensor([hi, lo, (lo + hi) / 3], dtype=torch.float64)
    with torch.no_grad():
        z, z2 = model.encode(x, mu), model.encode(x, mu2)
        backbone = model.encoder.backbone(model.encoder_input(x))
        torch.testing.assert_close(z, backbone + model.embed_param(mu), rtol=0, atol=1e-12)
        torch.testing.assert_close(z2 - z, model.embed_param(mu2) - model.embed_param(mu), rtol=0, atol=1e-12)
        assert (model.embed_param(mu2) - model.embed_param(mu)).abs().max() > 1e-3  # the embedding does depend on mu


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_sensor_local_jacobian_and_inference_decoder_on_cuda_match_cpu():
    model = build_model("burgers", "mlp", r=4, preset="lite", seed=0).double()
    z = torch.randn(3, 4, dtype=torch.float64)
    mu = _mu_grid("burgers", 3)
    sensors = np.stack([np.r_[0, 5, 511, 1023]] * 3)
    rows = lambda n: sensors.repeat(n // 3, axis=0)  # noqa: E731
    out = {}
    for device in ("cpu", "cuda"):
        m = model.to(device)
        h, J = m.filter_observe_jacobian(mu.to(device), rows, "u")(z.to(device))
        with torch.no_grad():
            fields = m.decode(z.to(device), mu.to(device))
            readings = m.observe(z.to(device), mu.to(device), sensors, "u")  # from the sensors' windows
        out[device] = (h.cpu(), J.cpu(), fields.cpu(), readings.cpu())
    for a, b in zip(out["cuda"], out["cpu"]):
        torch.testing.assert_close(a, b, rtol=1e-10, atol=1e-12)


def test_dense_derivatives_refuse_a_layer_without_a_rule():
    """fc_jacobian and fc_vjp know Linear layers and exact GELUs only; anything else is an error that names it,
    not a wrong Jacobian."""
    from dks_gym.models.dense_derivatives import fc_jacobian, fc_vjp

    layers = torch.nn.Sequential(torch.nn.Linear(3, 4), torch.nn.Tanh(), torch.nn.Linear(4, 5))
    x = torch.randn(2, 3)
    with pytest.raises(TypeError, match="no Jacobian rule for Tanh"):
        fc_jacobian(layers, x)
    with pytest.raises(TypeError, match="no Jacobian rule for Tanh"):
        fc_vjp(layers, x, torch.randn(2, 6, 5))
