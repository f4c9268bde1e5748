"""Configs: presets, files, precedence and errors that name the field."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from msmem_core.config import METHODS, load_config
from msmem_core.errors import UserError


@pytest.mark.parametrize("method", METHODS)
def test_every_preset_resolves(method):
    cfg = load_config(method)
    assert cfg.method == method
    assert cfg.skills[0].name == "view"


def test_file_overrides_preset_and_flags_override_file(tmp_path):
    f = tmp_path / "c.yaml"
    f.write_text("steps: 7\nseed: 3\nig:\n  ray_stride_px: 16\n")
    cfg = load_config("view-only", f, {"steps": 5})
    assert (cfg.steps, cfg.seed, cfg.ig.ray_stride_px) == (5, 3, 16)
    assert cfg.objective[0].name == "ig"  # untouched preset value survives


def test_every_method_runs_under_one_set_of_rules_and_a_file_restores_mems():
    """Every preset caps the evidence a manipulation changed and stops manipulating at step 25
    (docs/explanation/msas.md); examples/mem-rules.yaml brings MEM's rules back."""
    from msmem_core.config import METHODS

    rules = {m: load_config(m).msas for m in METHODS}
    assert {(r.disturbed_evidence_cap, r.manipulation_window, r.disturbed_margin_voxels, r.failed_manipulation_cap)
            for r in rules.values()} == {(4.0, (3, 25), 2, 4.0)}
    for method in METHODS:
        mem = load_config(method, Path(__file__).parents[1] / "examples" / "mem-rules.yaml").msas
        assert (mem.disturbed_evidence_cap, mem.manipulation_window) == (None, (3, 38))


def test_json_config_files_work(tmp_path):
    f = tmp_path / "c.json"
    f.write_text(json.dumps({"msas": {"tau_chi": 0.3}}))
    assert load_config(None, f).msas.tau_chi == 0.3


def test_unknown_key_is_rejected_with_dotted_path(tmp_path):
    f = tmp_path / "c.yaml"
    f.write_text("msas:\n  tau_chii: 0.3\n")
    with pytest.raises(UserError, match=r"field msas\.tau_chii: Extra inputs are not permitted"):
        load_config(None, f)


def test_wrong_type_is_rejected_with_dotted_path(tmp_path):
    f = tmp_path / "c.yaml"
    f.write_text("camera:\n  width_px: wide\n")
    with pytest.raises(UserError, match=r"c\.yaml.*field camera\.width_px: Input should be a valid integer"):
        load_config(None, f)


def test_bad_window_is_rejected():
    with pytest.raises(UserError, match=r"msas: Value error, manipulation_window"):
        load_config(None, None, {"msas": {"manipulation_window": [5, 2]}})


def test_unknown_method_lists_methods():
    with pytest.raises(UserError, match="methods: view-only, push-only, grasp-only, no-cdc, ours"):
        load_config("nosuch")


def test_unreadable_and_invalid_files_name_the_file(tmp_path):
    with pytest.raises(UserError, match=r"cannot read config file .*missing\.yaml"):
        load_config(None, tmp_path / "missing.yaml")
    bad = tmp_path / "bad.yaml"
    bad.write_text("a: [1, 2\n")
    with pytest.raises(UserError, match=r"bad\.yaml is not valid YAML"):
        load_config(None, bad)
    lst = tmp_path / "list.yaml"
    lst.write_text("- 1\n")
    with pytest.raises(UserError, match="mapping at the top level"):
        load_config(None, lst)


def test_the_library_defaults_come_from_one_file_and_a_component_naming_another_replaces_it_whole() -> None:
    """``msmem_core/presets/defaults.yaml`` is what a run without a file gets, and what ``RunConfig()``
    gets; a file naming another observation or effect model does not inherit the default's parameters
    (the learned push model's ``weights`` would be refused by ``push-analytic``), while one naming the
    same model keeps them and adds its own."""
    from msmem_core.config import RunConfig, deep_merge, library_defaults, load_config

    d = library_defaults()
    cfg = load_config("ours")
    assert cfg.observation_model.model_dump() == RunConfig().observation_model.model_dump()
    assert cfg.observation_model.name == d["observation_model"]["name"]
    assert {k: v.model_dump() for k, v in cfg.effect_models.items()} == {
        k: {"params": {}, **v} for k, v in d["effect_models"].items()}
    swapped = load_config("ours", None, {"effect_models": {"push": {"name": "push-analytic"}}})
    assert swapped.effect_models["push"].model_dump() == {"name": "push-analytic", "params": {}}
    assert swapped.effect_models["grasp"] == cfg.effect_models["grasp"]
    same = load_config("ours", None, {"effect_models": {"push": {"name": "cnabu-push", "params": {"threads": 1}}}})
    assert same.effect_models["push"].params == {**cfg.effect_models["push"].params, "threads": 1}
    assert deep_merge({"a": {"name": "x", "params": {"k": 1}}}, {"a": {"params": {"j": 2}}}) == {
        "a": {"name": "x", "params": {"k": 1, "j": 2}}}
