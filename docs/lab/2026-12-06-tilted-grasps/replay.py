"""Replay one recorded grasp in the run's scene, freshly settled, logging the gripper's contacts per physics step.

The first grasp of an episode comes after views only, which move nothing, so the settled scene is the
one the grasp met. Usage (from the repository root)::

    python replay.py RUN_DIR STEP [--cfg CFG.yaml] [--mod key=value ...] [--quiet]

``RUN_DIR`` is a ``msmem run`` folder (``scene.json``, ``steps.jsonl``). Modifications (``--mod``):
``d=`` the pre-grasp pose this far back along the approach (the gripper travels in at its height);
``dz=`` the grasp, its approach and its retreat shifted up (m); ``target=`` the object id to watch
(default: the one nearest the contact); ``tmass=``, ``tfric=``, ``tspin=``, ``troll=`` the target's
mass and lateral, spinning and rolling friction; ``allfric=`` every object's lateral friction;
``fingerfric=`` the fingers'. It reads the PyBullet backend's private state (its client, bodies and
physics step), so it is a lab tool, not an API.
"""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path
from typing import Any

import numpy as np
import pybullet as p
from msmem_grasp.skill import GraspAction

from msmem_core.cli.app import _pm
from msmem_core.config import load_config
from msmem_core.msas import fallen_or_left
from msmem_core.run.runner import run_wide
from msmem_core.world.scene import SceneSpec

FRICTION = {"tfric": "lateralFriction", "tmass": "mass", "tspin": "spinningFriction", "troll": "rollingFriction"}


def modified_action(act: dict[str, Any], mods: dict[str, str]) -> GraspAction:
    """The recorded action with ``dz`` and ``d`` applied."""
    act = dict(act)
    dz = float(mods.get("dz", 0.0))
    if dz:
        pose = [list(r) for r in act["pose"]]
        pose[2][3] += dz
        act["pose"] = pose
        act["approach_m"] = [[x, y, z + dz] for x, y, z in act["approach_m"]]
        act["retreat_m"] = [[x, y, z + dz] for x, y, z in act["retreat_m"]]
        act["contact_m"] = [*act["contact_m"][:2], act["contact_m"][2] + dz]
    if "d" in mods:
        pose = np.array(act["pose"])
        pre = pose[:3, 3] - float(mods["d"]) * pose[:3, 2]
        act["approach_m"] = [[pre[0], min(-0.12, pre[1]), pre[2]], pre.tolist()]
    return GraspAction.model_validate(act)


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("run")
    ap.add_argument("step", type=int)
    ap.add_argument("--cfg", default=None)
    ap.add_argument("--method", default="grasp-only")
    ap.add_argument("--mod", nargs="*", default=[])
    ap.add_argument("--quiet", action="store_true")
    ap.add_argument("--every", type=int, default=12, help="physics steps between log lines")
    args = ap.parse_args()
    mods = dict(m.split("=") for m in args.mod)
    run = Path(args.run)

    cfg = load_config(args.method, args.cfg, {"scene": {"file": str(run / "scene.json")}})
    pm = _pm()
    common = run_wide(cfg)
    sim: Any = pm.build("simulator", cfg.simulator, where="simulator", **common)
    skill = next(pm.build("skill", r, where="skill", **common) for r in cfg.skills if r.name == "grasp")
    scene = SceneSpec.model_validate_json((run / "scene.json").read_text())
    records = [json.loads(line) for line in (run / "steps.jsonl").read_text().splitlines()]
    recorded = next(r for r in records if r["step"] == args.step)["action"]
    action = modified_action(recorded, mods)

    sim.reset(scene)
    client, objects = sim._client, sim._objects
    names: dict[int, Any] = {o.uid: i for i, o in objects.items()}
    names.update({u: "shelf" for u in sim._shelf_uids})
    names[sim._gripper_uid] = "gripper"
    before = sim.object_poses()
    target = int(mods.get("target", -1))
    if target < 0:
        contact = np.array(action.contact_m)
        target = min(objects, key=lambda i: float(np.linalg.norm(before[i][:3, 3] - contact)))
    tu = objects[target].uid
    for i, o in objects.items():
        kw = {"lateralFriction": float(mods["allfric"])} if "allfric" in mods else {}
        if i == target:
            kw |= {FRICTION[k]: float(v) for k, v in mods.items() if k in FRICTION}
        if kw:
            p.changeDynamics(o.uid, -1, physicsClientId=client, **kw)
    if "fingerfric" in mods:
        for link in (-1, 0, 1):
            p.changeDynamics(sim._gripper_uid, link, lateralFriction=float(mods["fingerfric"]), physicsClientId=client)

    info = p.getDynamicsInfo(tu, -1, physicsClientId=client)
    lo, hi = p.getAABB(tu, physicsClientId=client)
    pose = np.array(action.pose)
    print(f"target {target} {scene.objects[target].class_name}: mass {info[0]:.3f}, friction lateral {info[1]:.2f} "
          f"rolling {info[6]:.1e} spinning {info[7]:.1e}; AABB {np.round(lo, 3)} {np.round(hi, 3)}")
    print(f"grasp at {np.round(pose[:3, 3], 3)}, closing b {np.round(pose[:3, 0], 3)}, approach a "
          f"{np.round(pose[:3, 2], 3)}, width {action.width_m:.4f}, opening {action.opening_m:.3f}")
    print(f"approach {np.round(action.approach_m, 3).tolist()}, retreat {np.round(action.retreat_m, 3).tolist()}")

    phase, count, first = ["init"], [0], set()
    physics_step = sim._physics_step

    def logged() -> None:
        physics_step()
        count[0] += 1
        forces: dict[tuple[int, Any], float] = {}
        for pt in p.getContactPoints(bodyA=sim._gripper_uid, physicsClientId=client):
            if pt[8] <= 1e-3:  # penetrating or touching
                key = (pt[3], names.get(pt[2], pt[2]))
                forces[key] = forces.get(key, 0.0) + pt[9]
        for key in forces.keys() - first:
            first.add(key)
            print(f"  first contact: gripper link {key[0]} with {key[1]} at step {count[0]} ({phase[0]})")
        if args.quiet or count[0] % args.every or target not in sim._objects:
            return
        pos, orn = p.getBasePositionAndOrientation(tu, physicsClientId=client)
        tilt = math.degrees(math.acos(float(np.clip(np.array(p.getMatrixFromQuaternion(orn))[8], -1.0, 1.0))))
        grip = np.round(sim.gripper_pose()[:3, 3], 3)
        print(f"{count[0]:5d} {phase[0]:8s} gripper {grip} target {np.round(pos, 3)} tilt {tilt:5.1f} "
              f"contacts {({k: round(v, 1) for k, v in forces.items()})}")

    sim._physics_step = logged
    calls, depth = {"move_gripper": 0, "set_gripper": 0}, [0]
    for name in calls:
        method = getattr(sim, name)

        def wrapped(*a: Any, _method: Any = method, _name: str = name, **k: Any) -> Any:
            if depth[0] == 0:  # a move sets the fingers itself: name the skill's own calls only
                phase[0] = f"{'move' if _name == 'move_gripper' else 'fingers'}{calls[_name]}"
                calls[_name] += 1
                print(f"-- {phase[0]} at step {count[0]}")
            depth[0] += 1
            try:
                return _method(*a, **k)
            finally:
                depth[0] -= 1

        setattr(sim, name, wrapped)
    # move0: in front of the shelf and in to the pre-grasp pose; move1: along the approach; fingers0: close
    out = skill.execute(sim, action, None)
    after = sim.object_poses()
    moved = {i: round(float(np.linalg.norm(after[i][:3, 3] - before[i][:3, 3])), 3) for i in before if i in after}
    fell = fallen_or_left(before, after, scene.shelf, removed=out.removed)
    far = {i: d for i, d in moved.items() if d > 0.01}
    print(f"RESULT success {out.success}, fell or left {fell}, moved > 1 cm {far}")


if __name__ == "__main__":
    main()
