"""Policy files without pickle (issue 24): weights as NPZ arrays loaded into a network built from the metadata,
format version checked, files only beside the JSON, tampered files refused with an error naming them; the loud
checkpoint selection of train_rl (issue 23)."""
from __future__ import annotations

import io
import json
import warnings
import zipfile

import numpy as np
import pytest

pytest.importorskip("stable_baselines3")

from control.rl.pipeline import PipelineConfig
from control.rl.policy import (
    FORMAT_VERSION,
    POLICY_DIR,
    PolicyFileError,
    available_policies,
    build_sb3_policy,
    convert_policy,
    load_policy,
    save_policy,
)
from scr_env.envs.core import OBS_BASE

OBS = np.array([500.0, 550.0, 5.0, 100.0, -1.0], dtype=np.float32)


def _save(tmp_path, algo="ppo", name="p", seed=0):
    import torch

    torch.manual_seed(seed)
    cfg = PipelineConfig(action="anr")
    kwargs = {"net_arch": [16, 16]} if algo != "ppo" else {"net_arch": {"pi": [16], "vf": [16]}, "log_std_init": -1.0}
    net = build_sb3_policy(algo, cfg.output_size, kwargs)
    meta = {"algo": algo.upper(), "observation_names": list(OBS_BASE), "env_kwargs": {}, "pipeline": cfg.to_dict(),
            "hyperparameters": {"policy_kwargs": kwargs}}
    rng = np.random.default_rng(seed)
    return save_policy(net, rng.normal(size=cfg.output_size), rng.uniform(1, 2, cfg.output_size), tmp_path, name,
                       meta), net


@pytest.mark.parametrize("algo", ["ppo", "sac", "td3"])
def test_saved_policy_is_arrays_and_reloads_identically(tmp_path, algo):
    path, net = _save(tmp_path, algo)
    meta = json.loads(path.read_text())
    assert meta["format_version"] == FORMAT_VERSION == 2
    assert meta["files"] == {"model": "p_policy.npz", "normalizer": "p_vecnormalize.npz"}
    with np.load(tmp_path / "p_policy.npz", allow_pickle=False) as z:
        assert set(z.files) == set(net.state_dict())
    pol = load_policy(path)
    a, _ = pol.predict(OBS, episode_start=np.array([True]))
    x = pol.normalize(np.asarray(pol._pipe.output()))
    ref, _ = net.predict(x, deterministic=True)
    np.testing.assert_allclose(a, pol._pipe.to_env_action(ref)[0], atol=1e-7)


def test_shipped_policies_are_state_dict_arrays():
    names = available_policies()
    assert {"ppo", "sac"} <= set(names)
    assert not list(POLICY_DIR.glob("*.zip")), "shipped policies must not be SB3 zips"
    for name in ("ppo", "sac"):
        meta = json.loads((POLICY_DIR / f"{name}.json").read_text())
        assert meta["format_version"] == 2
        for f in meta["files"].values():
            assert "/" not in f and (POLICY_DIR / f).is_file()
        a, _ = load_policy(name).predict(OBS, episode_start=np.array([True]))
        assert np.isfinite(a).all()


def _tamper(path, **changes):
    meta = json.loads(path.read_text())
    for k, v in changes.items():
        if k == "model_file":
            meta["files"]["model"] = v
        else:
            meta[k] = v
    path.write_text(json.dumps(meta))


@pytest.mark.parametrize("change, match", [
    ({"format_version": 99}, "format_version 99"),
    ({"format_version": "2"}, "format_version"),
    ({"model_file": "../p_policy.npz"}, "own folder"),
    ({"model_file": "/etc/passwd"}, "own folder"),
    ({"model_file": "missing.npz"}, "does not exist"),
    ({"algo": "DQN"}, "cannot build"),
    ({"hyperparameters": {"policy_kwargs": {"net_arch": [32, 32]}}}, "do not fit|shape"),
])
def test_tampered_metadata_is_refused_naming_the_file(tmp_path, change, match):
    path, _ = _save(tmp_path, "sac")
    _tamper(path, **change)
    with pytest.raises(PolicyFileError, match=match) as exc:
        load_policy(path)
    assert str(path) in str(exc.value) or "p_policy.npz" in str(exc.value)


def test_damaged_weights_are_refused(tmp_path):
    path, _ = _save(tmp_path, "ppo")
    weights = tmp_path / "p_policy.npz"
    with np.load(weights) as z:
        arrays = {k: z[k] for k in z.files}
    key = next(iter(arrays))
    bad = dict(arrays, **{key: np.full_like(arrays[key], np.nan)})
    np.savez(weights, **bad)
    with pytest.raises(PolicyFileError, match="finite"):
        load_policy(path)
    short = dict(arrays, **{key: arrays[key][..., :-1]})
    np.savez(weights, **short)
    with pytest.raises(PolicyFileError, match="shape"):
        load_policy(path)
    obj = dict(arrays, **{key: np.array([{"x": 1}], dtype=object)})
    np.savez(weights, **obj)  # an object array is pickled in the NPZ: refused, never unpickled
    with pytest.raises(PolicyFileError, match="p_policy.npz"):
        load_policy(path)
    weights.write_bytes(b"not an npz")
    with pytest.raises(PolicyFileError, match="p_policy.npz"):
        load_policy(path)


def test_version_1_zip_reads_only_the_state_dict(tmp_path):
    """A format-1 policy (an SB3 zip) loads from its ``policy.pth`` member by torch weights_only; the zip's pickled
    ``data`` member is never read (here it is garbage that no unpickler could take)."""
    import torch

    path, net = _save(tmp_path, "sac")
    buf = io.BytesIO()
    torch.save(net.state_dict(), buf)
    with zipfile.ZipFile(tmp_path / "p.zip", "w") as z:
        z.writestr("data", b"\x80\x04cos\nsystem\n(S'echo pwned'\ntR.")
        z.writestr("policy.pth", buf.getvalue())
    meta = json.loads(path.read_text())
    meta.update(format_version=1, files={"model": "p.zip", "normalizer": "p_vecnormalize.npz"})
    v1 = tmp_path / "v1.json"
    v1.write_text(json.dumps(meta))
    a1, _ = load_policy(v1).predict(OBS, episode_start=np.array([True]))
    a2, _ = load_policy(path).predict(OBS, episode_start=np.array([True]))
    np.testing.assert_array_equal(a1, a2)
    new = convert_policy(v1, tmp_path / "converted", "c")
    assert json.loads(new.read_text())["format_version"] == 2
    a3, _ = load_policy(new).predict(OBS, episode_start=np.array([True]))
    np.testing.assert_array_equal(a1, a3)


def test_selection_is_loud_when_no_checkpoint_is_within_the_limit():
    from control.rl.selection import SlipLimitWarning, select

    rows = [{"candidate": "a.json", "mean_nh3_slip_ppm_max": 30.0, "tailpipe_nox_g_per_kwh_mean": 0.1},
            {"candidate": "b.json", "mean_nh3_slip_ppm_max": 2988.0, "tailpipe_nox_g_per_kwh_mean": 0.05}]
    with pytest.warns(SlipLimitWarning, match="NO CANDIDATE WITHIN THE SLIP LIMIT"):
        best = select(rows)
    assert best["candidate"] == "a.json" and best["within_slip_limit"] is False
    rows.append({"candidate": "c.json", "mean_nh3_slip_ppm_max": 9.0, "tailpipe_nox_g_per_kwh_mean": 0.3})
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        best = select(rows)
    assert best["candidate"] == "c.json" and best["within_slip_limit"] is True
