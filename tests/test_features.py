"""Feature networks for LPIPS / FID / FVD: architectures, weight loading, conversion, Frechet distance.

Pretrained weights are not available offline, so every test writes randomly initialised weights of
the standard architecture and loads them the way real weights are loaded.
"""

from pathlib import Path

import numpy as np
import pytest
import torch
from safetensors.torch import save_file

from iwsim.core.checkpoint import CheckpointError
from iwsim.core.errors import IwsimError
from iwsim.eval import features as ft


def _random_state(cls: type[torch.nn.Module], seed: int) -> dict[str, torch.Tensor]:
    """A random state dict of the architecture, with non-trivial BatchNorm statistics."""
    torch.manual_seed(seed)
    model = cls()
    for m in model.modules():
        if isinstance(m, (torch.nn.BatchNorm2d, torch.nn.BatchNorm3d)):
            m.running_mean.uniform_(-0.1, 0.1)
            m.running_var.uniform_(0.5, 1.5)
    state = {k: v.detach().clone().contiguous() for k, v in model.state_dict().items()}
    if cls is ft.LPIPS:
        # The official "lin" weights are non-negative, which makes distances non-negative.
        for k in state:
            if k.startswith("lin"):
                state[k] = state[k].abs()
    return state


@pytest.fixture(scope="module")
def states() -> dict[str, dict[str, torch.Tensor]]:
    return {"lpips": _random_state(ft.LPIPS, 0), "inception": _random_state(ft.InceptionFID, 1),
            "i3d": _random_state(ft.I3D, 2)}


@pytest.fixture(scope="module")
def weights(tmp_path_factory: pytest.TempPathFactory, states: dict[str, dict[str, torch.Tensor]]) -> Path:
    """A weights directory holding all three safetensors files."""
    d = tmp_path_factory.mktemp("weights")
    for kind, name in (("lpips", ft.LPIPS_FILE), ("inception", ft.INCEPTION_FILE), ("i3d", ft.I3D_FILE)):
        save_file(states[kind], d / name)
    return d


def _assert_loaded(model: torch.nn.Module, state: dict[str, torch.Tensor]) -> None:
    loaded = model.state_dict()
    assert set(loaded) == set(state)
    for k, v in state.items():
        assert torch.equal(loaded[k], v), k


# ---- weights directory -------------------------------------------------------------------------


def test_weights_dir_honours_env(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    monkeypatch.setenv(ft.WEIGHTS_ENV, str(tmp_path / "w"))
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "xdg"))
    assert ft.weights_dir() == tmp_path / "w"


def test_weights_dir_defaults(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    monkeypatch.delenv(ft.WEIGHTS_ENV, raising=False)
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "xdg"))
    assert ft.weights_dir() == tmp_path / "xdg" / "iwsim" / "weights"
    monkeypatch.delenv("XDG_CACHE_HOME")
    monkeypatch.setenv("HOME", str(tmp_path))
    assert ft.weights_dir() == tmp_path / ".cache" / "iwsim" / "weights"


# ---- architectures -----------------------------------------------------------------------------


def _count(model: torch.nn.Module, prefix: str = "") -> int:
    return sum(p.numel() for k, p in model.named_parameters() if k.startswith(prefix))


def test_parameter_counts_match_standard_nets() -> None:
    lpips = ft.LPIPS()
    assert _count(lpips, "features.") == 2_469_696  # torchvision alexnet().features
    assert _count(lpips, "lin") == 64 + 192 + 384 + 256 + 256
    # torchvision inception_v3 has 27,161,264 parameters (its weights' meta "num_params"); without
    # AuxLogits (3,326,696) and with a 1008-class instead of a 1000-class fc this is pytorch-fid's net.
    assert _count(ft.InceptionFID()) == 27_161_264 - 3_326_696 - (2048 * 1000 + 1000) + (2048 * 1008 + 1008)
    i3d = ft.I3D()
    # pytorch-i3d's InceptionI3d: 12,287,264 below the logits, plus a 1x1x1 conv 1024 -> 400 with bias.
    assert _count(i3d) - _count(i3d, "logits.") == 12_287_264
    assert _count(i3d) == 12_287_264 + 1024 * 400 + 400


def test_key_names_are_the_official_ones() -> None:
    tv_alexnet_features = {f"features.{i}.{p}" for i in (0, 3, 6, 8, 10) for p in ("weight", "bias")}
    lpips_lins = {f"lin{i}.model.1.weight" for i in range(5)}
    assert set(ft.LPIPS().state_dict()) == tv_alexnet_features | lpips_lins

    inception = ft.InceptionFID().state_dict()
    for key in ("Conv2d_1a_3x3.conv.weight", "Conv2d_1a_3x3.bn.running_var", "Mixed_5b.branch_pool.conv.weight",
                "Mixed_6e.branch7x7dbl_5.bn.bias", "Mixed_7c.branch3x3dbl_3b.conv.weight", "fc.bias"):
        assert key in inception
    assert inception["fc.weight"].shape == (1008, 2048)
    assert inception["Mixed_6b.branch7x7_2.conv.weight"].shape == (128, 128, 1, 7)
    assert not any(k.startswith("AuxLogits") for k in inception)

    i3d = ft.I3D().state_dict()
    for key in ("Conv3d_1a_7x7.conv3d.weight", "Conv3d_1a_7x7.bn.weight", "Mixed_3b.b0.conv3d.weight",
                "Mixed_5c.b2b.bn.running_mean", "logits.conv3d.weight", "logits.conv3d.bias"):
        assert key in i3d
    assert i3d["Conv3d_1a_7x7.conv3d.weight"].shape == (64, 3, 7, 7, 7)
    assert i3d["logits.conv3d.weight"].shape == (400, 1024, 1, 1, 1)


# ---- loading and running -----------------------------------------------------------------------


def test_lpips_loads_and_measures(monkeypatch: pytest.MonkeyPatch, weights: Path, states: dict) -> None:
    monkeypatch.setenv(ft.WEIGHTS_ENV, str(weights))
    model = ft.load_lpips()
    assert not model.training
    _assert_loaded(model, states["lpips"])
    g = torch.Generator().manual_seed(0)
    a, b = torch.rand(2, 3, 64, 64, generator=g), torch.rand(2, 3, 64, 64, generator=g)
    same, different = model(a, a), model(a, b)
    assert same.shape == different.shape == (2,)
    assert torch.allclose(same, torch.zeros(2))
    assert (different > 0).all()
    with pytest.raises(ValueError, match="equal shape"):
        model(a, b[:1])


def test_inception_loads_and_embeds(monkeypatch: pytest.MonkeyPatch, weights: Path, states: dict) -> None:
    monkeypatch.setenv(ft.WEIGHTS_ENV, str(weights))
    model = ft.load_inception()
    assert not model.training
    _assert_loaded(model, states["inception"])
    out = model(torch.rand(2, 3, 64, 64, generator=torch.Generator().manual_seed(0)))
    assert out.shape == (2, 2048)
    assert torch.isfinite(out).all()


@pytest.mark.slow
def test_i3d_loads_and_embeds(monkeypatch: pytest.MonkeyPatch, weights: Path, states: dict) -> None:
    monkeypatch.setenv(ft.WEIGHTS_ENV, str(weights))
    model = ft.load_i3d()
    assert not model.training
    _assert_loaded(model, states["i3d"])
    out = model(torch.rand(1, 16, 3, 64, 64, generator=torch.Generator().manual_seed(0)))
    assert out.shape == (1, 400)
    assert torch.isfinite(out).all()
    with pytest.raises(ValueError, match="at least 9 frames"):
        model(torch.rand(1, 8, 3, 64, 64))


@pytest.mark.parametrize("loader, filename", [(ft.load_lpips, ft.LPIPS_FILE), (ft.load_inception, ft.INCEPTION_FILE),
                                              (ft.load_i3d, ft.I3D_FILE)])
def test_missing_weights_name_the_file(monkeypatch: pytest.MonkeyPatch, tmp_path: Path, loader, filename: str) -> None:
    monkeypatch.setenv(ft.WEIGHTS_ENV, str(tmp_path))
    with pytest.raises(ft.WeightsMissing, match=filename) as e:
        loader()
    assert isinstance(e.value, IwsimError)
    assert e.value.filename == filename and e.value.directory == tmp_path
    assert str(e.value) == f"{filename} not found in {tmp_path}"
    with pytest.raises(ft.WeightsMissing):
        loader(tmp_path / "elsewhere")


def test_mismatched_weights_raise_checkpoint_error(tmp_path: Path, states: dict) -> None:
    state = dict(states["lpips"])
    state["lin5.model.1.weight"] = state.pop("lin4.model.1.weight")
    save_file(state, tmp_path / ft.LPIPS_FILE)
    with pytest.raises(CheckpointError, match="lin4.model.1.weight"):
        ft.load_lpips(tmp_path)

    state = dict(states["lpips"])
    state["lin0.model.1.weight"] = torch.zeros(1, 65, 1, 1)
    save_file(state, tmp_path / ft.LPIPS_FILE)
    with pytest.raises(CheckpointError, match="wrong shapes"):
        ft.load_lpips(tmp_path)

    (tmp_path / ft.LPIPS_FILE).write_bytes(b"not safetensors")
    with pytest.raises(CheckpointError, match="safetensors"):
        ft.load_lpips(tmp_path)


# ---- converting official files -----------------------------------------------------------------


def test_convert_lpips_merges_alexnet_and_lin(tmp_path: Path, states: dict) -> None:
    state = states["lpips"]
    # A torchvision alexnet file also holds the classifier, which LPIPS does not use.
    alexnet = {k: v for k, v in state.items() if k.startswith("features.")} | {"classifier.1.weight": torch.zeros(4, 9)}
    lins = {k: v for k, v in state.items() if k.startswith("lin")}
    torch.save(alexnet, tmp_path / "alexnet-owt.pth")
    torch.save(lins, tmp_path / "alex.pth")
    out = ft.convert("lpips", [tmp_path / "alexnet-owt.pth", tmp_path / "alex.pth"], tmp_path / "w")
    assert out == tmp_path / "w" / ft.LPIPS_FILE
    assert sorted(p.name for p in out.parent.iterdir()) == [ft.LPIPS_FILE]  # no temporary left behind
    _assert_loaded(ft.load_lpips(out.parent), state)


@pytest.mark.parametrize("kind, source", [("inception", "pt_inception-2015-12-05.pth"), ("i3d", "rgb_imagenet.pt")])
def test_convert_single_file(monkeypatch: pytest.MonkeyPatch, tmp_path: Path, states: dict, kind: str,
                             source: str) -> None:
    state = states[kind]
    # Files saved by old PyTorch versions have no BatchNorm num_batches_tracked buffers.
    torch.save({k: v for k, v in state.items() if not k.endswith("num_batches_tracked")}, tmp_path / source)
    monkeypatch.setenv(ft.WEIGHTS_ENV, str(tmp_path / "w"))
    out = ft.convert(kind, [tmp_path / source])
    model = ft.load_inception() if kind == "inception" else ft.load_i3d()
    assert out.parent == tmp_path / "w"
    loaded = model.state_dict()
    for k, v in state.items():
        if not k.endswith("num_batches_tracked"):
            assert torch.equal(loaded[k], v), k


def test_convert_rejects_bad_sources(tmp_path: Path, states: dict) -> None:
    with pytest.raises(ValueError, match="unknown weights kind"):
        ft.convert("vgg", [tmp_path / "x.pth"], tmp_path)
    with pytest.raises(ValueError, match="2 source file"):
        ft.convert("lpips", [tmp_path / "x.pth"], tmp_path)
    with pytest.raises(CheckpointError, match="missing"):
        ft.convert("i3d", [tmp_path / "absent.pt"], tmp_path)
    # An LPIPS file given where the alexnet file belongs: the trunk is missing, nothing is written.
    lins = {k: v for k, v in states["lpips"].items() if k.startswith("lin")}
    torch.save(lins, tmp_path / "alex.pth")
    with pytest.raises(CheckpointError, match="missing keys"):
        ft.convert("lpips", [tmp_path / "alex.pth", tmp_path / "alex.pth"], tmp_path / "w")
    assert not (tmp_path / "w").exists()


# ---- Frechet distance --------------------------------------------------------------------------


def _with_moments(rng: np.random.Generator, n: int, mean: np.ndarray, cov: np.ndarray) -> np.ndarray:
    """n samples whose sample mean and (unbiased) sample covariance are exactly mean and cov."""
    x = rng.standard_normal((n, len(mean)))
    x -= x.mean(0)
    x = x @ np.linalg.inv(np.linalg.cholesky(np.cov(x, rowvar=False))).T
    return x @ np.linalg.cholesky(cov).T + mean


def test_frechet_distance_of_a_set_with_itself_is_zero() -> None:
    x = np.random.default_rng(0).standard_normal((200, 16)) * 3 + 1
    assert abs(ft.frechet_distance(x, x)) < 1e-8


def test_frechet_distance_matches_closed_form_for_diagonal_gaussians() -> None:
    rng = np.random.default_rng(1)
    mu_a, mu_b = np.array([0.0, 1.0, -2.0, 0.5]), np.array([1.0, 1.0, 0.0, -0.5])
    var_a, var_b = np.array([1.0, 4.0, 0.25, 2.0]), np.array([2.0, 1.0, 1.0, 0.5])
    a = _with_moments(rng, 300, mu_a, np.diag(var_a))
    b = _with_moments(rng, 500, mu_b, np.diag(var_b))
    # Commuting covariances: Tr(Sa + Sb - 2 (Sa Sb)^(1/2)) = sum (sqrt(va) - sqrt(vb))^2.
    expected = np.sum((mu_a - mu_b) ** 2) + np.sum((np.sqrt(var_a) - np.sqrt(var_b)) ** 2)
    assert ft.frechet_distance(a, b) == pytest.approx(expected, rel=1e-9)


def test_frechet_distance_matches_symmetric_form_for_full_covariances() -> None:
    rng = np.random.default_rng(2)
    d = 6
    m_a, m_b = rng.standard_normal((d, d)), rng.standard_normal((d, d))
    s_a, s_b = m_a @ m_a.T + 0.1 * np.eye(d), m_b @ m_b.T + 0.1 * np.eye(d)
    mu_a, mu_b = rng.standard_normal(d), rng.standard_normal(d)
    a, b = _with_moments(rng, 100, mu_a, s_a), _with_moments(rng, 100, mu_b, s_b)
    # Tr (Sa Sb)^(1/2) = Tr (Sa^(1/2) Sb Sa^(1/2))^(1/2), a symmetric PSD root computed by eigh.
    w, v = np.linalg.eigh(s_a)
    root_a = (v * np.sqrt(w)) @ v.T
    tr_covmean = np.sum(np.sqrt(np.clip(np.linalg.eigvalsh(root_a @ s_b @ root_a), 0, None)))
    expected = np.sum((mu_a - mu_b) ** 2) + np.trace(s_a) + np.trace(s_b) - 2 * tr_covmean
    assert ft.frechet_distance(a, b) == pytest.approx(expected, rel=1e-7)


def test_frechet_distance_handles_singular_covariances() -> None:
    rng = np.random.default_rng(3)
    a, b = rng.standard_normal((4, 10)), rng.standard_normal((5, 10)) + 1  # fewer samples than dims
    value = ft.frechet_distance(a, b)
    assert np.isfinite(value) and value > 0


def test_frechet_distance_of_few_samples_equals_the_full_covariances_form() -> None:
    """Fewer samples than dimensions (the singular case pytorch-fid regularises): the
    factored trace equals Tr (Sa^(1/2) Sb Sa^(1/2))^(1/2) of the d x d covariances, and a
    set with itself is at distance 0."""
    rng = np.random.default_rng(4)
    a, b = rng.standard_normal((5, 40)) * 2, rng.standard_normal((7, 40)) + 0.5
    s_a, s_b = np.cov(a, rowvar=False), np.cov(b, rowvar=False)
    w, v = np.linalg.eigh(s_a)
    root_a = (v * np.sqrt(np.clip(w, 0, None))) @ v.T
    tr_covmean = np.sum(np.sqrt(np.clip(np.linalg.eigvalsh(root_a @ s_b @ root_a), 0, None)))
    diff = a.mean(0) - b.mean(0)
    expected = diff @ diff + np.trace(s_a) + np.trace(s_b) - 2 * tr_covmean
    # the reference sums the square roots of ~35 roundoff-level eigenvalues (each up to ~1e-7)
    assert ft.frechet_distance(a, b) == pytest.approx(expected, abs=1e-4)
    assert abs(ft.frechet_distance(a, a)) < 1e-9
    # one set with more samples than dimensions, the other fewer: the two factors mix
    c = rng.standard_normal((60, 40))
    s_c = np.cov(c, rowvar=False)
    tr_ac = np.sum(np.sqrt(np.clip(np.linalg.eigvalsh(root_a @ s_c @ root_a), 0, None)))
    diff = a.mean(0) - c.mean(0)
    assert ft.frechet_distance(a, c) == pytest.approx(diff @ diff + np.trace(s_a) + np.trace(s_c) - 2 * tr_ac,
                                                      abs=1e-4)


def test_frechet_distance_rejects_bad_input() -> None:
    x = np.zeros((10, 3))
    with pytest.raises(ValueError, match="at least 2 samples"):
        ft.frechet_distance(x[:1], x)
    with pytest.raises(ValueError, match="equal dimension"):
        ft.frechet_distance(x, np.zeros((10, 4)))
    with pytest.raises(ValueError, match=r"\(N, D\)"):
        ft.frechet_distance(np.zeros(10), x)
