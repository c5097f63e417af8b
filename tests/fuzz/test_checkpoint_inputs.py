"""Fuzz: both trainers' checkpoints corrupted (bytes, and well-formed files of wrong content)
and given to ``--resume``: one line and exit 2 before training, and the run as it was."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch
from fuzz.conftest import check, copy_tree, invoke, odd_dir
from fuzz.mutate import Case, byte_cases

SEED = 4300

# ------------------------------------------------------------------------------ checkpoints
def _torch_case(cid: str, change) -> Case:
    def apply(path: Path) -> None:
        st = torch.load(path, map_location="cpu", weights_only=False)
        change(st)
        torch.save(st, path)
    return Case(cid, apply)


def _set(keys, value):
    def change(st):
        node = st
        for k in keys[:-1]:
            node = node[k]
        node[keys[-1]] = value(node[keys[-1]]) if callable(value) else value
    return change


def _drop(keys):
    def change(st):
        node = st
        for k in keys[:-1]:
            node = node[k]
        del node[keys[-1]]
    return change


def _nan(t: torch.Tensor) -> torch.Tensor:
    t = t.clone()
    t.view(-1)[0] = float("nan")
    return t


def _checkpoint_semantic(kind: str) -> list[Case]:
    common = [_torch_case("not-a-dict", lambda st: st.clear() or st.update({"x": 1})),
              _torch_case("version-99", _set(("version",), 99)),
              _torch_case("missing-version", _drop(("version",))),
              _torch_case("step-string", _set(("step",), "12")),
              _torch_case("step-negative", _set(("step",), -5)),
              _torch_case("seconds-nan", _set(("seconds",), float("nan"))),
              _torch_case("history-number", _set(("history",), 3))]
    if kind == "static":
        return common + [
            _torch_case("missing-field", _drop(("field",))),
            _torch_case("field-res-zero", _set(("field", "res"), 0)),
            _torch_case("field-config-unknown-key", _set(("field", "config"), lambda c: {**c, "zz": 1})),
            _torch_case("field-active-out-of-range", _set(("field", "active"), lambda t: t + 10 ** 9)),
            _torch_case("field-active-negative", _set(("field", "active"), lambda t: t - 10 ** 9)),
            _torch_case("field-density-nan", _set(("field", "density"), _nan)),
            _torch_case("field-density-short", _set(("field", "density"), lambda t: t[:-1])),
            _torch_case("field-sh-wrong-width", _set(("field", "sh"), lambda t: t[:, :-1])),
            _torch_case("field-volume-radius-negative", _set(("field", "volume", "radius"), -1.0)),
            _torch_case("field-tensor-is-list", _set(("field", "density"), [1.0, 2.0])),
        ]
    return common + [
        _torch_case("missing-model", _drop(("model",))),
        _torch_case("model-key-missing", lambda st: st["model"].pop(next(iter(st["model"])))),
        _torch_case("model-tensor-wrong-shape", lambda st: st["model"].update(
            {k: v[..., :1] for k, v in list(st["model"].items())[:1]})),
        _torch_case("model-nan", lambda st: st["model"].update(
            {k: _nan(v) for k, v in list(st["model"].items()) if v.is_floating_point()})),
        _torch_case("config-unknown-key", _set(("config",), lambda c: {**c, "zz": 1})),
        _torch_case("config-deter-zero", _set(("config", "deter"), 0)),
        _torch_case("missing-opt", _drop(("opt",))),
        _torch_case("opt-garbage", _set(("opt",), {"state": 1})),
    ]


CKPT_BYTES = byte_cases(SEED + 2, truncate_at=(0.0, 0.05, 0.5, 0.95), flips=((1, "head"), (16, "middle"), (64, "any")))


def _resume(capfd, tmp_path, run_src: Path, ds: Path, case: Case, command: tuple[str, ...]):
    run = copy_tree(run_src, odd_dir(tmp_path) / "run")
    case.apply(run / "checkpoint.pt")
    before = sorted(p.name for p in run.iterdir())
    res = invoke(capfd, "dbb-train", *command[:1], ds, "-o", run, "--resume", *command[1:])
    # A flipped byte inside a tensor's data is a changed weight: training goes on from it.
    check(res, None, may_pass=case.id.startswith("flip-16-middle") or case.id.startswith("flip-64"))
    if res.code == 2:
        assert sorted(p.name for p in run.iterdir()) == before, "a refused resume changed the run"
        assert not (run.parent / ".run.work").exists() or not any((run.parent / ".run.work").iterdir())
    assert not [p.name for p in run.parent.iterdir() if ".partial-" in p.name or ".old-" in p.name]


@pytest.mark.parametrize("case", CKPT_BYTES + _checkpoint_semantic("static"), ids=lambda c: c.id)
def test_checkpoint_plenoctree(capfd, tmp_path, static_run, case: Case):
    folder, _ = static_run
    _resume(capfd, tmp_path, folder / "run", folder / "ds", case, ("plenoctree", "--steps", "21"))


@pytest.mark.parametrize("case", CKPT_BYTES + _checkpoint_semantic("dynamic"), ids=lambda c: c.id)
def test_checkpoint_rssm(capfd, tmp_path, dynamic_run, case: Case):
    _resume(capfd, tmp_path, dynamic_run / "run", dynamic_run / "ds", case, ("rssm", "--steps", "4"))

