"""Settings are checked when a config is built: each rule rejects a bad value with an error naming
the field, its value and what is allowed, before any work; every shipped config passes."""

import dataclasses
import math
import pickle
import re

import pytest

from skillplug_jax import cli, experiment, losses, validation
from skillplug_jax.experiment import Experiment, FewShot, Trainable, Variant
from skillplug_jax.losses import LossWeights
from skillplug_jax.model import config as model_config
from skillplug_jax.model import plug as plug_module
from skillplug_jax.model.config import ModelConfig
from skillplug_jax.model.plug import PlugConfig
from skillplug_jax.train import config, run_record
from skillplug_jax.train.config import TrainConfig

TRAIN = TrainConfig(preset="quick", model=ModelConfig())
BASE = {"model": ModelConfig(), "plug": PlugConfig(), "loss": LossWeights(), "train": TRAIN, "fewshot": FewShot(),
        "trainable": Trainable(), "experiment": Experiment(train=TRAIN)}
SECTION = {"model": "model.", "plug": "model.plug.", "loss": "loss.", "train": "", "fewshot": "fewshot.",
           "trainable": "fewshot.trainable.", "experiment": ""}
NAN, INF = math.nan, math.inf

# (config, field, a value its rule rejects): every rule, and for ranges each side of it
REJECTED = [
    ("model", "policy", "diffusion"), ("model", "use_images", "yes"), ("model", "cameras", ()),
    ("model", "cameras", ("side", "side")), ("model", "cameras", ("top",)), ("model", "cameras", ["side"]),
    ("model", "instruction_vocab", -1), ("model", "instruction_words", 0), ("model", "proprio", ()), ("model", "proprio", ("joint_pos", "joint_pos")), ("model", "proprio", ("eef_rot",)),
    ("model", "image_size", (64,)), ("model", "image_size", (0, 64)), ("model", "joint_dim", 0),
    ("model", "action_dim", 0), ("model", "chunk", 0), ("model", "hidden", 0), ("model", "heads", 0),
    ("model", "ff", 0), ("model", "enc_layers", -1), ("model", "dec_layers", 0),
    ("model", "decoder_first_layer_only", 1), ("model", "dropout", -0.1), ("model", "dropout", 1.5),
    ("model", "dropout", NAN), ("model", "positions", "both"), ("model", "embed_init_std", -0.02),
    ("model", "pre_norm", "true"), ("model", "cvae_zero_init", None), ("model", "normalize_object_state", 0),
    ("model", "latent_dim", 0), ("model", "cvae_enc_layers", -1), ("model", "backbone_width", 0),
    ("model", "backbone_stages", ()), ("model", "backbone_stages", (2, 0, 2)),
    ("plug", "num_skills", 0), ("plug", "num_skills", 2.5), ("plug", "num_skills", True),
    ("plug", "skill_latent_dim", 0), ("plug", "alignment_dim", 0), ("plug", "interactor", "attention"),
    ("plug", "router_temperature", 0.0), ("plug", "router_temperature", INF), ("plug", "site", "middle"),
    ("plug", "skill_offset", "zero"), ("plug", "router_input", "zero_style"), ("model", "object_tokens", "many"),
    ("plug", "router_cue_slots", -1), ("model", "dtype", "int8"), ("model", "dtype", "float16"),
    ("plug", "fusion_weights", "top1"), ("model", "adapter_width", -1),
    ("model", "hidden", 100),  # not divisible by the 8 heads
    ("model", "object_tokens", "per_object"),  # with use_images=True
    *[("loss", name, bad) for name in ("rec", "kl", "bsa", "sd", "cvae_kl", "usage", "router_label")
                             for bad in (-0.1, NAN)],
    ("loss", "sd", INF), ("loss", "sd_kind", "cos"), ("loss", "sd_usage_weighted", "yes"),
    ("train", "preset", ""), ("train", "taskset", ""), ("train", "demos", 0), ("train", "data_seed", -1),
    ("train", "data_dir", ""), ("train", "backend", "bullet"), ("train", "batch_size", 0), ("train", "lr", 0.0),
    ("train", "lr", -1e-4), ("train", "lr", NAN), ("train", "weight_decay", -1e-4), ("train", "grad_clip", NAN),
    ("train", "warmup_steps", -1), ("train", "lr_schedule", "linear"), ("train", "epochs", 0.0),
    ("train", "max_steps", -5), ("train", "seed", -1), ("train", "trainable", ("encoderr",)),
    ("train", "trainable", ("router", "router")), ("train", "log_every", 0), ("train", "ckpt_every", 0),
    ("train", "keep_checkpoints", 0), ("train", "skill_labels", "phases"),
    ("fewshot", "taskset", ""), ("fewshot", "demos", 0), ("fewshot", "steps", -1),
    ("fewshot", "trainable", ("router",)), ("fewshot", "marginal_terms", "no"), ("fewshot", "train_overrides", "loss.sd=0"),
    ("fewshot", "per", "suite"),
    ("trainable", "act", ("head",)), ("trainable", "skillplug", ("router", "router")),
    ("trainable", "act", ["action_head"]),
    ("experiment", "policies", ()), ("experiment", "policies", ("act", "act")),
    ("experiment", "policies", ("diffusion",)), ("experiment", "seeds", ()), ("experiment", "seeds", (0, 0)),
    ("experiment", "seeds", (-1,)), ("experiment", "trials", 0), ("experiment", "eval_seed", -1),
    ("experiment", "eval_batch", 0), ("experiment", "run_fewshot", "no"), ("experiment", "workers", 0),
    ("experiment", "variants", (Variant("a"), Variant("a"))), ("experiment", "variants", (Variant(""),)),
    ("experiment", "variants", (Variant("a/b"),)), ("experiment", "variants", (Variant(".x"),)),
    ("experiment", "variants", (Variant("a", adapts="b"),)),  # adapts no arm of the experiment
    ("experiment", "variants", (Variant("a"), Variant("b", adapts="a"), Variant("c", adapts="b"))),
]

# Values at the edge of a rule that mean something and must stay allowed.
ACCEPTED = [
    ("model", "enc_layers", 0), ("model", "cvae_enc_layers", 0), ("model", "dropout", 0.0),
    ("model", "dropout", 1.0), ("model", "embed_init_std", 0.0), ("plug", "num_skills", 1),
    ("model", "dtype", "bfloat16"), ("model", "cameras", ("wrist",)), ("model", "cameras", ("agentview", "eye_in_hand")), ("plug", "router_cue_slots", 0),
    ("plug", "fusion_weights", "uniform"), ("model", "adapter_width", 0),
    *[("loss", name, 0.0) for name in ("rec", "kl", "bsa", "sd", "cvae_kl")],
    ("train", "max_steps", 0), ("train", "warmup_steps", 0), ("train", "grad_clip", 0.0),
    ("train", "grad_clip", -1.0), ("train", "weight_decay", 0.0), ("train", "trainable", ()),
    ("train", "epochs", 0.5), ("train", "lr", 1), ("train", "backend", "mjx-warp"),
    ("train", "skill_labels", ""), ("train", "skill_labels", "tabletop_phases"),
    ("fewshot", "steps", 0), ("trainable", "act", ("action_proj",)), ("trainable", "skillplug", ()),
    ("experiment", "seeds", (2, 0)), ("experiment", "policies", ("skillplug",)), ("experiment", "workers", 1),
]


def _case_id(case):
  return f"{case[0]}.{case[1]}={case[2]!r}"


@pytest.mark.parametrize("case", REJECTED, ids=_case_id)
def test_each_rule_rejects_a_bad_value_naming_field_value_and_range(case):
  kind, field, bad = case
  with pytest.raises(validation.ConfigError) as info:
    dataclasses.replace(BASE[kind], **{field: bad})
  message = str(info.value)
  assert message.startswith(f"{SECTION[kind]}{field} must be "), message
  assert info.value.field == field
  shown = [v.name for v in bad] if field == "variants" else bad
  assert info.value.allowed and message.endswith(f"must be {info.value.allowed}, got {shown!r}"), message


@pytest.mark.parametrize("case", ACCEPTED, ids=_case_id)
def test_edge_values_that_mean_something_are_accepted(case):
  kind, field, value = case
  changed = dataclasses.replace(BASE[kind], **{field: value})
  assert getattr(changed, field) == value


def test_every_rejected_field_has_a_rule_and_every_rule_a_case():
  tables = {"model": model_config._RULES, "plug": plug_module._RULES, "loss": losses._WEIGHT_RULES,
            "train": config._RULES, "fewshot": run_record._FEWSHOT_RULES, "trainable": run_record._TRAINABLE_RULES,
            "experiment": experiment._EXPERIMENT_RULES}
  covered = {(kind, field) for kind, field, _ in REJECTED}
  for kind, rules in tables.items():
    missing = {f for f in rules if (kind, f) not in covered}
    assert not missing, f"{kind}: rules without a test case: {missing}"
  names = {kind: {f.name for f in dataclasses.fields(BASE[kind])} for kind in BASE}
  assert all(field in names[kind] for kind, field, _ in REJECTED + ACCEPTED)


def test_the_messages_read_as_documented():
  with pytest.raises(ValueError, match=re.escape("model.plug.num_skills must be an integer >= 1, got 0")):
    PlugConfig(num_skills=0)
  with pytest.raises(ValueError, match=re.escape("model.hidden must be divisible by heads (8), got 100")):
    ModelConfig(hidden=100)
  with pytest.raises(ValueError, match=re.escape("max_steps must be an integer >= 0 (0: train `epochs`), got -5")):
    dataclasses.replace(TRAIN, max_steps=-5)
  with pytest.raises(ValueError, match=re.escape("model.dropout must be in [0, 1], got 1.5")):
    ModelConfig(dropout=1.5)
  with pytest.raises(ValueError, match=re.escape("loss.kl must be >= 0, got -1.0")):
    LossWeights(kl=-1.0)
  with pytest.raises(ValueError, match="state-only"):
    ModelConfig(use_images=True, object_tokens="per_object")
  assert ModelConfig(use_images=False, object_tokens="per_object").object_tokens == "per_object"
  libero = ("joint_pos", "gripper_qpos", "eef_pos", "eef_quat")
  with pytest.raises(ValueError, match=re.escape(f"model.joint_dim must be the width of proprio {libero} (16), got 7")):
    ModelConfig(proprio=libero)
  assert ModelConfig(proprio=libero, joint_dim=16).joint_dim == 16


def test_overrides_name_the_key_they_were_given():
  cfg = experiment.preset("quick")
  for key, value, shown in (("model.plug.num_skills", "0", "0"), ("max_steps", "-5", "-5"), ("loss.sd", "-1", "-1.0"),
                            ("lr", "0", "0.0"), ("model.policy", "diffusion", "'diffusion'")):
    with pytest.raises(validation.ConfigError, match=re.escape(f"{key} must be ")) as info:
      config.override(cfg, [f"{key}={value}"])
    assert str(info.value).startswith(key) and str(info.value).endswith(f"got {shown}")
  for key, value in (("train.model.plug.num_skills", "0"), ("train.max_steps", "-5"), ("train.loss.kl", "-1"),
                     ("fewshot.steps", "-1"), ("fewshot.demos", "0"), ("seeds", "0,0"), ("trials", "0")):
    with pytest.raises(validation.ConfigError) as info:
      experiment.get("cpu", [f"{key}={value}"])
    assert str(info.value).startswith(f"{key} must be "), str(info.value)
  # a variant's own overrides are checked too, named from the experiment
  exp = dataclasses.replace(experiment.get("quick"), variants=(Variant("bad", ("train.model.heads=3",)),))
  with pytest.raises(validation.ConfigError, match=re.escape("train.model.hidden must be divisible by heads (3)")):
    experiment.expand(exp)


def test_overrides_are_checked_together_not_one_by_one():
  cfg = experiment.preset("quick")  # hidden 64, heads 4
  assert config.override(cfg, ["model.heads=3", "model.hidden=96"]).model.heads == 3  # 64 % 3 in between
  assert config.override(cfg, ["model.plug.num_skills=0", "model.plug.num_skills=3"]).model.plug.num_skills == 3
  with pytest.raises(validation.ConfigError, match=re.escape("model.hidden must be divisible by heads (5)")):
    config.override(cfg, ["model.hidden=96", "model.heads=5"])
  with pytest.raises(validation.ConfigError):  # the checks are back on after an override, failed or not
    PlugConfig(num_skills=0)


def test_the_command_line_stops_before_any_work(capsys, tmp_path):
  for setting, named in (("model.plug.num_skills=0", "model.plug.num_skills must be an integer >= 1, got 0"),
                         ("max_steps=-5", "max_steps must be an integer >= 0")):
    rc = cli.main(["pretrain", "--config", "quick", "--set", setting, "--workdir", str(tmp_path / "run")])
    assert rc == 2
    assert named in capsys.readouterr().err
  assert not (tmp_path / "run").exists()


def test_a_recorded_config_is_checked_when_read():
  d = config.to_dict(TRAIN)
  d["model"]["plug"]["num_skills"] = 0
  with pytest.raises(validation.ConfigError, match=re.escape("model.plug.num_skills must be an integer >= 1, got 0")):
    config.from_dict(d)


def _flat_record(cfg: TrainConfig, **model_extra) -> dict:
  """`cfg` as a config.json written before issue 40 holds it: the plug's settings flat in `model`
  (plug_site for site), and the arms since removed at their neutral values."""
  d = config.to_dict(cfg)
  plug = d["model"].pop("plug")
  plug["plug_site"] = plug.pop("site")
  del plug["fusion_weights"], d["model"]["adapter_width"]  # added since (issue 43): absent, at their defaults
  d["model"].update(plug)
  d["model"].update(dict(routing="soft", fusion_source="router"), **model_extra)
  d["loss"].update(load_balance=0.0, router_z=0.0, distill=1.0)
  return d


def test_a_config_from_before_the_plug_module_loads_as_it_was_trained():
  cfg = experiment.preset("cpu")
  cfg = config.override(cfg, ["model.plug.num_skills=6", "model.plug.site=decoder", "loss.usage=0.5"])
  assert config.from_dict(_flat_record(cfg)) == cfg
  for arm, value in (("routing", "top1"), ("fusion_source", "posterior"), ("router_input", "zero_style"),
                     ("dtype", "float16")):
    with pytest.raises(ValueError, match=f"removed in issue 40.*{model_config.REMOVED_AT}"):
      config.from_dict(_flat_record(cfg, **{arm: value}))
  d = _flat_record(cfg)
  d["loss"]["router_z"] = 1e-3
  with pytest.raises(ValueError, match=r"loss.router_z=0.001.*removed in issue 40|removed in issue 40.*router_z"):
    config.from_dict(d)


def test_every_shipped_config_builds():
  for name in experiment.names():
    exp = experiment.get(name)
    for _, arm in experiment.expand(exp):
      for policy in arm.policies:
        for seed in arm.seeds:
          assert arm.train_config(policy, seed).model.policy == policy
  assert experiment.get("toy_skills").train.preset == "toy_skills"  # the toy problem's config


def test_the_error_pickles_with_its_fields():  # a pipeline worker's error reaches the parent whole
  err = pickle.loads(pickle.dumps(validation.ConfigError("num_skills", 0, "an integer >= 1", "model.plug.")))
  assert str(err) == "model.plug.num_skills must be an integer >= 1, got 0" and err.field == "num_skills"


def test_the_fewshot_groups_are_one_setting_from_config_to_optimizer():
  exp = experiment.get("quick", ["fewshot.trainable.act=action_proj", "fewshot.trainable.skillplug=router,action_proj"])
  assert exp.fewshot.trainable == Trainable(act=("action_proj",), skillplug=("router", "action_proj"))
  assert exp.fewshot.trainable.of("skillplug") == ("action_proj", "router")  # sorted, as TrainConfig.trainable
  assert experiment.get("quick").fewshot.trainable.of("act") == ("action_head",)
  with pytest.raises(ValueError, match=re.escape("unknown policy 'diffusion'")):
    Trainable().of("diffusion")
  with pytest.raises(validation.ConfigError, match=re.escape("fewshot.trainable.skillplug must be ")):
    experiment.get("quick", ["fewshot.trainable.skillplug=head"])
  with pytest.raises(ValueError, match=re.escape("fewshot.trainable holds settings (act, skillplug)")):
    experiment.get("quick", ["fewshot.trainable=router"])
  with pytest.raises(ValueError, match=re.escape("unknown setting 'fewshot.trainable_act'")):
    experiment.get("quick", ["fewshot.trainable_act=router"])  # the old key: named, not ignored


def test_a_record_from_before_trainable_loads_its_groups():
  """config.json records written when the groups were FewShot.trainable_act / trainable_skillplug."""
  new = run_record.record_to_dict(experiment.record(experiment.get("quick"), "skillplug"))
  old = dict(new, fewshot={k: v for k, v in new["fewshot"].items() if k != "trainable"})
  old["fewshot"].update(trainable_act=["action_proj"], trainable_skillplug=["router", "action_proj"])
  loaded = run_record.record_from_dict(old)
  assert loaded.fewshot.trainable == Trainable(act=("action_proj",), skillplug=("router", "action_proj"))
  assert dataclasses.replace(loaded.fewshot, trainable=Trainable()) == FewShot(steps=new["fewshot"]["steps"])
  del old["fewshot"]["marginal_terms"], old["fewshot"]["trainable_act"]  # older still: the defaults
  assert run_record.record_from_dict(old).fewshot.trainable == Trainable(skillplug=("router", "action_proj"))
  # today's records read back as written, through JSON
  import json
  assert run_record.record_from_dict(json.loads(json.dumps(new))) == run_record.record_from_dict(new)
  assert new["fewshot"]["trainable"] == {"act": ("action_head",), "skillplug": ("action_head", "router")}
