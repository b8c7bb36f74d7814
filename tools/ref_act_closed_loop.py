"""The reference ACT (LeRobot's PyTorch ACT) trained on our data and evaluated in our engine.

Issue 12's yardstick: does our ACT learn as well as the reference ACT on the
same demonstrations, batches and budget? This trains `lerobot.policies.act`
at the `quick` preset's shapes and optimiser on the dataset our
`experiments/act_parity.py` trains on, with our `ChunkLoader`'s batches
(the same (seed, step) -> batch draws, the same normalisation), then rolls
it out closed loop through our episode engine (`skillplug_jax.evaluate.
protocol.evaluate_task`: the same seeded, paired trials and success checks)
with our temporal ensembling (k = 0.01, every step). Only the network and
its training step are LeRobot's.

It needs torch and lerobot beside the project, so it runs in its own virtual
environment, never the project's (it is a reference, not a dependency):

    python3 -m venv /tmp/refvenv   # then the three pip lines of ../shared/tools/ref_act_bench.py's docstring
    echo "$PWD/.venv/lib/python3.11/site-packages" > /tmp/refvenv/lib/python3.11/site-packages/project.pth
    echo "$PWD" >> /tmp/refvenv/lib/python3.11/site-packages/project.pth
    /tmp/refvenv/bin/python tools/ref_act_closed_loop.py --taskset quickstart3 --seeds 0,1,2

LeRobot 0.6.1 declares Python >= 3.12; on 3.11 the PEP 695 import shim of
`../shared/tools/ref_act_bench.py` is used (imported from there, not copied).
Results: OUT/<taskset>_seed<S>.json per seed (reused when present) and
OUT/summary_<taskset>.{json,md}.
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

import envs
from envs.rollout import Controller
from skillplug_jax.atomic_json import write_json_atomic, write_text_atomic
from skillplug_jax.data import loader as data_loader
from skillplug_jax.evaluate import protocol
from skillplug_jax.evaluate.policy_controller import temporal_ensemble
from skillplug_jax.experiment import preset
from skillplug_jax.train import config, loop

SHARED_TOOLS = Path(__file__).resolve().parents[2] / "shared" / "tools"


def lerobot_act(model):
  sys.path.insert(0, str(SHARED_TOOLS))
  from ref_act_bench import import_lerobot_act, install_py311_shim
  install_py311_shim()
  ACTConfig, ACTPolicy, FeatureType, PolicyFeature, _ = import_lerobot_act()
  cfg = ACTConfig(
      input_features={
          "observation.state": PolicyFeature(type=FeatureType.STATE, shape=(model.joint_dim,)),
          "observation.environment_state": PolicyFeature(type=FeatureType.ENV, shape=(envs.OBJECT_STATE_DIM,))},
      output_features={"action": PolicyFeature(type=FeatureType.ACTION, shape=(model.action_dim,))},
      device="cpu", chunk_size=model.chunk, n_action_steps=model.chunk, dim_model=model.hidden,
      n_heads=model.heads, dim_feedforward=model.ff, n_encoder_layers=model.enc_layers,
      n_decoder_layers=model.dec_layers, use_vae=True, latent_dim=model.latent_dim,
      n_vae_encoder_layers=model.cvae_enc_layers, dropout=model.dropout, kl_weight=10.0,
      pretrained_backbone_weights=None)
  return ACTPolicy(cfg)


def train(cfg: config.TrainConfig, data, torch):
  """LeRobot's ACT on our batches: AdamW, linear warm-up, global-norm clipping as cfg says."""
  torch.manual_seed(cfg.seed)
  policy = lerobot_act(cfg.model)
  policy.train()
  opt = torch.optim.AdamW(policy.parameters(), lr=cfg.lr, weight_decay=cfg.weight_decay)
  warm = max(cfg.warmup_steps, 1)
  sched = torch.optim.lr_scheduler.LambdaLR(opt, lambda s: min(1.0, s / warm) if cfg.warmup_steps else 1.0)
  ld = data_loader.ChunkLoader(data, cfg.batch_size, chunk=cfg.model.chunk, seed=cfg.seed,
                               normalize_object_state=cfg.model.normalize_object_state)
  steps = cfg.num_steps(data.num_episodes)
  losses = []
  for step in range(steps):
    b = ld.numpy_batch(step)
    batch = {"observation.state": torch.from_numpy(b["joint_pos"]),
             "observation.environment_state": torch.from_numpy(b["object_state"]),
             "action": torch.from_numpy(b["actions"]),
             "action_is_pad": torch.from_numpy(~b["action_mask"])}
    loss, _ = policy.forward(batch)
    opt.zero_grad()
    loss.backward()
    if cfg.grad_clip > 0:
      torch.nn.utils.clip_grad_norm_(policy.parameters(), cfg.grad_clip)
    opt.step()
    sched.step()
    losses.append(loss.item())
  policy.eval()
  return policy, losses


def controller(policy, model, stats, torch) -> Controller:
  """Our controller's input normalisation and temporal ensembling around LeRobot's chunk."""
  st = {k: {s: jnp.asarray(stats[k][s], jnp.float32) for s in ("mean", "std")} for k in stats
        if k in ("action", "joint_pos", "object_state")}

  def predict_chunk(joint_pos, object_state):
    with torch.no_grad():
      out = policy.predict_action_chunk({"observation.state": torch.from_numpy(np.array(joint_pos)),
                                         "observation.environment_state": torch.from_numpy(np.array(object_state))})
    return out.numpy().astype(np.float32)

  def init(state):
    b = state.obs["joint_pos"].shape[0]
    return jnp.zeros((b, model.chunk, model.chunk, model.action_dim), jnp.float32)

  def act(weights, buf, state, t):
    obs = state.obs
    joint = (obs["joint_pos"] - st["joint_pos"]["mean"]) / st["joint_pos"]["std"]
    obj = envs.padded_object_state(obs["object_state"])
    if model.normalize_object_state:
      obj = (obj - st["object_state"]["mean"]) / st["object_state"]["std"]
    shape = jax.ShapeDtypeStruct((joint.shape[0], model.chunk, model.action_dim), jnp.float32)
    pred = jax.pure_callback(predict_chunk, shape, joint, obj)
    pred = pred * st["action"]["std"] + st["action"]["mean"]
    action, buf = temporal_ensemble(buf, pred, t, 0.01)
    return action, buf, {}

  return Controller(init, act, 0, "reference ACT (LeRobot)", ())


def main(argv=None) -> int:
  p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
  p.add_argument("--taskset", default="quickstart3")
  p.add_argument("--seeds", default="0,1,2")
  p.add_argument("--trials", type=int, default=50)
  p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                 help="overrides of the quick ACT config (e.g. model.normalize_object_state=false)")
  p.add_argument("--data-dir", default="results/act_parity/datasets")
  p.add_argument("--threads", type=int, default=1, help="torch.set_num_threads")
  p.add_argument("--out", default="results/act_parity/reference")
  args = p.parse_args(argv)
  import torch
  torch.set_num_threads(args.threads)
  envs.quiet_warp()
  out = Path(args.out)
  tasks = envs.taskset(args.taskset)
  per_seed = []
  for seed in [int(s) for s in args.seeds.split(",") if s]:
    path = out / f"{args.taskset}_seed{seed}.json"
    if path.exists():
      per_seed.append(json.loads(path.read_text()))
      continue
    cfg = config.override(preset("quick", "act"), args.set + [
        f"taskset={args.taskset}", f"seed={seed}", f"data_dir={args.data_dir}"])
    data = loop.load_data(cfg)
    t0 = time.time()
    policy, losses = train(cfg, data, torch)
    train_s = time.time() - t0
    ctrl = controller(policy, cfg.model, data.stats, torch)
    results = []
    for task in tasks:
      r = protocol.evaluate_task(task, ctrl, args.trials, batch=args.trials)
      results.append({k: r[k] for k in ("task", "abbr", "trials", "success_rate", "successes",
                                        "mean_steps_success", "trial_success")})
      print(f"[reference] seed {seed} {r['abbr']}: {100 * r['success_rate']:.0f}%", file=sys.stderr, flush=True)
    import lerobot
    rec = dict(seed=seed, overrides=args.set, train_s=round(train_s, 1), final_loss=losses[-1],
               torch=torch.__version__, lerobot=getattr(lerobot, "__version__", "?"), tasks=results)
    write_json_atomic(path, rec)
    per_seed.append(rec)
  rows = {}
  for i, task in enumerate(tasks):
    rates = [100 * s["tasks"][i]["success_rate"] for s in per_seed]
    rows[task] = dict(mean=statistics.fmean(rates), seeds=rates,
                      se=statistics.stdev(rates) / len(rates) ** 0.5 if len(rates) > 1 else 0.0)
  write_json_atomic(out / f"summary_{args.taskset}.json", dict(taskset=args.taskset, trials=args.trials,
                                                             overrides=args.set, rows=rows))
  text = "| | " + " | ".join(s["abbr"] for s in per_seed[0]["tasks"]) + " |\n|---|" + "---|" * len(tasks) + "\n"
  text += "| reference ACT | " + " | ".join(f"{r['mean']:.1f} ± {r['se']:.1f}" for r in rows.values()) + " |\n"
  write_text_atomic(out / f"summary_{args.taskset}.md", text)
  print(text)
  return 0


if __name__ == "__main__":
  sys.exit(main())
