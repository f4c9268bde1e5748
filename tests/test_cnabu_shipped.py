"""The shipped CNABU weights against held-out scenes (what docs/explanation/cnabu.md says of them).

``tests/data/cnabu_heldout/<kind>/`` holds shards made by ``msmem datagen cnabu --seed 10000`` (scene
seeds the training data never used, see ``plugins/msmem_cnabu/weights/MODEL_CARD.md``). On them:

- the shipped weights load (``weights_only=True``, sha256 of the sidecar) and beat "no change" in
  NLL where the action acts (a trivial baseline that every trained effect model must beat);
- the default belief model of each role is whichever of learned and analytic has the better
  held-out NLL (occupancy + semantics), as ``msmem eval belief-models`` decides: for push and grasp
  on the region the action affects, one prediction per sample; for observe, which is applied to
  every view of an episode, on the final belief of a closed-loop view-only episode on a generated
  scene no training data came from (two scenes, 40 steps: the setting of the docs' decision).
"""

from __future__ import annotations

from pathlib import Path

import pytest
from msmem_cnabu.learn.evaluation import evaluate
from msmem_cnabu.weights import load_cnabu, shipped_weights

from msmem_core.config import RunConfig
from msmem_core.plugins.manager import get_plugin_manager

HELDOUT = Path(__file__).parent / "data" / "cnabu_heldout"
KINDS = ("observe", "push", "grasp")
TWIN = {"observe": "analytic-observation", "push": "push-analytic", "grasp": "grasp-analytic"}


def default_model(kind: str) -> str:
    """The belief model a run uses for ``kind`` when its config names none."""
    if kind == "observe":
        return RunConfig().observation_model.name
    effect = get_plugin_manager().skills()[kind].effect_model
    assert effect is not None
    return effect


_HELDOUT: dict[str, dict] = {}
# observe's held-out check runs two closed-loop 40-step episodes: the slow suite's
KIND_PARAMS = [pytest.param("observe", marks=pytest.mark.slow), "push", "grasp"]


def heldout(kind: str) -> dict:
    """``msmem eval belief-models`` on the held-out shards of ``kind`` (computed once per session)."""
    if kind not in _HELDOUT:
        _HELDOUT[kind] = evaluate(kind, HELDOUT / kind, timing=False, threads=1, log=lambda _: None, episodes=2,
                                  episode_steps=40)
    return _HELDOUT[kind]


@pytest.mark.parametrize("kind", KINDS)
def test_shipped_weights_load_as_plain_tensors(kind):
    net, meta = load_cnabu(kind)
    assert meta["kind"] == kind
    assert not net.training
    assert shipped_weights(kind).stat().st_size < 4e6
    assert max(meta["data"]["manifest"]["seeds"]) < 10000  # the held-out scenes are seeds 10000 and up


@pytest.mark.parametrize("kind", KIND_PARAMS)
def test_shipped_weights_beat_no_change_on_heldout_scenes(kind):
    m = heldout(kind)["metrics"]
    assert heldout(kind)["samples"] >= 4
    nll = {k: m[k]["affected"]["occ_nll"] + m[k]["affected"]["sem_nll"] for k in ("learned", "no-change")}
    assert nll["learned"] < nll["no-change"], nll


@pytest.mark.parametrize("kind", KIND_PARAMS)
def test_default_model_per_role_is_the_one_with_better_heldout_nll(kind):
    """Of a role's learned CNABU model and its analytic twin, the one with the better held-out NLL is the
    default. The observation role has a third model: the whole-map ``cnabu-map`` is the
    default there, chosen by the map-prediction benchmark (docs/results.md), so the rule only says the
    per-view ``cnabu-observe`` is not the default while its twin is better."""
    better = heldout(kind)["better_nll"]
    want = f"cnabu-{kind}" if better == "learned" else TWIN[kind]
    why = (kind, heldout(kind)["metrics"]["learned"]["affected"], heldout(kind)["metrics"]["analytic"]["affected"])
    if kind == "observe" and default_model(kind) == "cnabu-map":
        assert want == TWIN[kind], why  # were cnabu-observe better than its twin, it would need a look
        return
    assert default_model(kind) == want, why


@pytest.mark.slow
def test_threshold_check_decides_twice_per_belief_and_a_lower_threshold_changes_more():
    from msmem_cnabu.learn.evaluation import threshold_agreement

    r = threshold_agreement("push", None, (0.85, 0.05), beliefs=1, views=4, threads=1, log=lambda _: None)
    assert r["decisions"] == 1
    hi, lo = r["beliefs"][0]["0.85"], r["beliefs"][0]["0.05"]
    assert r["beliefs"][0]["same"] == (hi["action"] == lo["action"] and hi["skill"] == lo["skill"])
    # deterministic (seeded scene and views): under the default IG a view wins on this belief at both
    # thresholds, so no push batch is reported; where a push wins, its nearly dense change map at 0.05
    # changes many more voxels per candidate
    assert hi["skill"] == lo["skill"]
    for row in (hi, lo):
        assert (row["changed_voxels_per_candidate"] is None) == (row["skill"] != "push")
    if hi["skill"] == "push":
        assert lo["changed_voxels_per_candidate"] > 3 * hi["changed_voxels_per_candidate"]


# The effect models fine-tuned on the completed beliefs of ``cnabu-map`` (MODEL_CARD_push_map.md,
# MODEL_CARD_grasp_map.md), the library defaults' (msmem_core/presets/defaults.yaml): on held-out actions from
# completed beliefs each must beat "no change" and the shipped model of its kind, which was trained on
# analytic beliefs; the push model also its analytic twin. The grasp twin believes the grasped region
# free (``target: free``), and the learned model (with ``grasped_region: free``) does not beat it:
# 1.50 against 1.23 nats (MODEL_CARD_grasp_map.md); both beat "no change" (3.16).
ON_MAP = {"push": "msmem_cnabu/weights/cnabu_push_map.pt", "grasp": "msmem_cnabu/weights/cnabu_grasp_map.pt"}


# the grasp case evaluates 4 scenes twice: the slow suite's (CI runs it), to keep `make test` under 5 minutes
@pytest.mark.parametrize("kind", ["push", pytest.param("grasp", marks=pytest.mark.slow)])
def test_map_weights_beat_the_twin_and_the_analytic_model_on_completed_beliefs(kind):
    from msmem_cnabu.weights import resolve_weights

    data = HELDOUT / f"{kind}_map"
    net, meta = load_cnabu(kind, ON_MAP[kind])
    assert not net.training
    assert resolve_weights(ON_MAP[kind]).stat().st_size < 4e6
    assert meta["data"]["manifest"]["config"]["observation_model"]["name"] == "cnabu-map"
    held = [int(p.stem.split("_")[1]) for p in data.glob("scene_*.npz")]
    assert held
    assert not set(held) & set(meta["data"]["manifest"]["seeds"])
    nll = {}
    for name, weights in (("map", resolve_weights(ON_MAP[kind])), ("shipped", None)):
        m = evaluate(kind, data, weights=weights, timing=False, threads=1, log=lambda _: None)["metrics"]
        nll[name] = m["learned"]["affected"]["occ_nll"] + m["learned"]["affected"]["sem_nll"]
        for base in ("analytic", "no-change"):
            nll[base] = m[base]["affected"]["occ_nll"] + m[base]["affected"]["sem_nll"]
    assert nll["map"] < min(nll["shipped"], nll["no-change"]), nll
    if kind == "push":
        assert nll["map"] < nll["analytic"], nll
    else:
        assert nll["analytic"] < nll["no-change"], nll
