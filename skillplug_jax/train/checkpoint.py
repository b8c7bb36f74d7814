"""A run's checkpoints: orbax saves and restores, and the integrity checks around them.

    <run>/checkpoints/<step>/          orbax: params, opt_state, step
    <run>/checkpoints/<step>/default/  ... and skillplug_checksums.json: each file's size and SHA-256

The JSON beside them (config.json, norm_stats.json) is `run_files`'s.

Orbax writes each checkpoint into a temporary directory and renames it when
complete, so a run killed mid-save keeps its previous checkpoint. A checkpoint
damaged afterwards (a truncated copy, a full disk, a bad sector) raises
DamagedCheckpoint naming its directory; a resumed training run then falls back
to the newest intact one (`restore_latest(..., fallback=True)`). Evaluation
reads only the latest checkpoint's parameters (`restore_params`).

Orbax's own checks miss changed bytes in the stored arrays (a flip inside
zstd-compressed data can decompress to other numbers), so each checkpoint
carries a manifest of its files' checksums, written into the item directory
when orbax finalizes it, before the rename that completes the checkpoint (a
checkpoint is never seen without it), and compared with every file before a
restore reads any. Checkpoints written before checksums were kept restore
without (a note says so).
"""

from __future__ import annotations

import dataclasses
import json
import sys
from pathlib import Path

import jax
import orbax.checkpoint as ocp
import tensorstore as ts

from skillplug_jax import checksums

CHECKSUMS = "skillplug_checksums.json"  # in each item directory (orbax's own files start with '_')
_KEPT = "skillplug_checksums"  # the step's custom metadata: the items hold a manifest


class CheckpointError(ValueError):
  """A checkpoint is missing, damaged, or was made by an incompatible configuration."""


class DamagedCheckpoint(CheckpointError):
  """A checkpoint's files are truncated, missing or corrupt (not a model mismatch)."""

  def __init__(self, path: Path, reason: str, advice: str = ""):
    self.path, self.reason, self.advice = Path(path), reason, advice
    super().__init__(f"checkpoint {path} is damaged (truncated, missing or corrupt files): {reason}"
                     + (f". {advice}" if advice else ""))

  def __reduce__(self):  # pickles (to another process) with its own arguments, not the message
    return type(self), (self.path, self.reason, self.advice)


def manager(run_dir: Path, keep: int = 2, params_only: bool = False) -> ocp.CheckpointManager:
  """The run's checkpoints. The item handler lets `restore` read a checkpoint's tree
  metadata before its arrays. `params_only`: a manager for `restore(..., params_only=True)`,
  which only reads: StandardCheckpointHandler cannot restore part of a tree, the
  PyTreeCheckpointHandler it wraps (the same files) can.

  Orbax reads every step's _CHECKPOINT_METADATA here, and one changed byte in it
  can make that fail (an unknown key): DamagedCheckpoint then names the file."""
  directory = (Path(run_dir) / "checkpoints").absolute()
  try:
    if params_only:
      return ocp.CheckpointManager(directory, options=ocp.CheckpointManagerOptions(create=False),
                                   item_handlers=ocp.PyTreeCheckpointHandler())
    return ocp.CheckpointManager(directory, options=ocp.CheckpointManagerOptions(max_to_keep=keep, create=True),
                                 item_handlers=ChecksummedHandler())
  except ValueError as e:
    _raise_if_step_metadata_damaged(directory, e)
    raise


def _raise_if_step_metadata_damaged(directory: Path, e: ValueError) -> None:
  """DamagedCheckpoint naming the newest step whose _CHECKPOINT_METADATA orbax cannot take."""
  from orbax.checkpoint._src.metadata import step_metadata_serialization
  for step in sorted((p for p in directory.iterdir() if p.name.isdigit()), key=lambda p: -int(p.name)):
    file = step / "_CHECKPOINT_METADATA"
    try:
      meta = json.loads(file.read_bytes())
    except (OSError, ValueError):  # orbax skips unreadable JSON; check_index names it at restore
      continue
    try:
      step_metadata_serialization.deserialize(meta)
    except Exception as bad:  # noqa: BLE001  orbax's checks of the keys and values
      raise DamagedCheckpoint(step, f"{file} is corrupt ({short_reason(bad)})",
                              f"Move or delete {step} to use the checkpoints before it") from e


class ChecksummedHandler(ocp.StandardCheckpointHandler):
  """StandardCheckpointHandler that writes the item's checksum manifest when orbax finalizes it.

  Orbax calls `finalize` once every process's files are written (and merged into
  one OCDBT index), while the item is still in its temporary directory: the
  manifest then lands with the rename that makes the checkpoint visible, so a
  kill at any moment leaves either no checkpoint or one with its manifest. The
  first process writes it (the others' files are on the shared disk by then).
  """

  def finalize(self, directory) -> None:
    super().finalize(directory)
    if jax.process_index() == 0:
      checksums.write_manifest(Path(str(directory)), CHECKSUMS)


# Orbax finds an item's handler by the exact class of its arguments.
@ocp.args.register_with_handler(ChecksummedHandler, for_save=True)
@dataclasses.dataclass
class ChecksummedSave(ocp.args.StandardSave):
  pass


@ocp.args.register_with_handler(ChecksummedHandler, for_restore=True)
@dataclasses.dataclass
class ChecksummedRestore(ocp.args.StandardRestore):
  pass


def save(mngr: ocp.CheckpointManager, step: int, state) -> None:
  """Start saving `state` as `step` (orbax finishes in the background; the step metadata
  records that the items carry checksums, so that a lost manifest is damage, not an old run)."""
  mngr.save(step, args=ChecksummedSave(state), custom_metadata={_KEPT: CHECKSUMS})


def step_dir(mngr: ocp.CheckpointManager, step: int) -> Path:
  return Path(mngr.directory) / str(step)


def restore(mngr: ocp.CheckpointManager, step: int, like, params_only: bool = False):
  """Restore into the structure, shapes and shardings of `like`.

  Raises CheckpointError when the checkpoint holds another model, and
  DamagedCheckpoint when its files cannot be read: the stored tree metadata
  is compared with `like` first, so a failure after that is the files' fault.
  params_only: `like` is the `params` subtree alone and only it is read (the
  optimiser state is not), with a `manager(..., params_only=True)`; leaves of
  `like` without a sharding go to the default device.
  """
  path = step_dir(mngr, step)
  abstract = jax.tree.map(ocp.utils.to_shape_dtype_struct, like)
  if params_only:
    device = jax.sharding.SingleDeviceSharding(jax.devices()[0])
    abstract = {"params": jax.tree.map(lambda x: x.update(sharding=x.sharding or device), abstract)}
  check_checksums(path)
  check_index(path)
  try:
    stored = mngr.item_metadata(step)
  except Exception:  # noqa: BLE001  unreadable tree metadata: the restore below says what is wrong
    stored = None
  if params_only and stored is not None:
    stored = {"params": stored.get("params", {})}
  misfit = "" if stored is None else tree_misfit(abstract, stored)
  if misfit:
    raise CheckpointError(f"checkpoint {path} does not fit this model: {misfit}")
  args = (ocp.args.PyTreeRestore(abstract, ocp.checkpoint_utils.construct_restore_args(abstract),
                                 partial_restore=True) if params_only
          else ChecksummedRestore(abstract))
  try:
    state = mngr.restore(step, args=args)
  except Exception as e:  # noqa: BLE001  orbax wraps TensorStore read errors in a bare Exception
    _raise_if_read_error(path, e)
    raise
  return state["params"] if params_only else state


def _raise_if_read_error(path: Path, e: Exception) -> None:
  """DamagedCheckpoint if `e` comes from reading files (TensorStore's ValueErrors, JSON and
  Unicode decoding, OSError); anything else (a bug, out of memory) is left to propagate."""
  if isinstance(innermost(e), (ValueError, OSError)):
    raise DamagedCheckpoint(path, short_reason(e)) from e


def restore_latest(mngr: ocp.CheckpointManager, like, fallback: bool = False, params_only: bool = False):
  """(state, step, damaged) of the newest checkpoint that restores (`params_only`: see `restore`).

  Without `fallback` a damaged newest checkpoint raises DamagedCheckpoint
  (evaluating an older one silently would mislabel results); with it, older
  ones are tried in turn and the damaged ones are returned for the caller to
  report and set aside. No checkpoint at all, or none intact: CheckpointError.
  """
  steps = sorted(mngr.all_steps(), reverse=True)
  if not steps:
    raise CheckpointError(f"{mngr.directory} has no checkpoint")
  damaged: list[DamagedCheckpoint] = []
  for i, step in enumerate(steps):
    try:
      return restore(mngr, step, like, params_only), step, damaged
    except DamagedCheckpoint as e:
      if not fallback:
        older = steps[i + 1] if i + 1 < len(steps) else None
        advice = ("No older checkpoint is kept: delete it and train again" if older is None else
                  f"Rerun the training command to set it aside and retrain from checkpoint {older}, "
                  f"or delete {e.path} to use checkpoint {older} instead")
        raise DamagedCheckpoint(e.path, e.reason, advice) from e
      damaged.append(e)
  raise CheckpointError(
      f"no intact checkpoint in {mngr.directory}: "
      + "; ".join(f"{e.path.name} is damaged ({e.reason})" for e in damaged)
      + f". Delete {mngr.directory} to train from the start")


def restore_params(run_dir: Path, like_params):
  """(params, step) of a run's latest checkpoint, for evaluation: shapes checked against
  `like_params`, the optimiser state not read, and no fallback to an older checkpoint
  (a damaged latest one raises DamagedCheckpoint naming it)."""
  mngr = manager(run_dir, params_only=True)
  try:
    params, step, _ = restore_latest(mngr, like_params, params_only=True)
  finally:
    mngr.close()
  return params, step


def manager_for_training(run_dir: Path, keep: int = 2) -> tuple[ocp.CheckpointManager, list]:
  """(manager, [(DamagedCheckpoint, where it went), ...]) for a run that resumes.

  Orbax reads every step's _CHECKPOINT_METADATA when it opens the directory, so
  a corrupt one stops `manager` before any checkpoint can be restored. Training
  moves that step aside as `set_aside` does and opens the directory again, so
  that it resumes from the newest intact checkpoint, as for damaged array files.
  """
  moved = []
  while True:
    try:
      return manager(run_dir, keep), moved
    except DamagedCheckpoint as e:
      if not e.path.exists() or any(e.path == bad.path for bad, _ in moved):
        raise  # nothing left to move: not a damaged step's metadata
      moved.append((DamagedCheckpoint(e.path, e.reason), _move_aside(e.path, run_dir)))  # advice done


def set_aside(mngr: ocp.CheckpointManager, damaged: DamagedCheckpoint, run_dir: Path) -> Path:
  """Move a damaged checkpoint to <run>/damaged_checkpoints/<step>[.N] and return where.

  Orbax would otherwise keep it as the latest step and skip saving that step
  again; it is moved rather than deleted so that it can still be looked at.
  """
  dst = _move_aside(damaged.path, run_dir)
  mngr.reload()
  return dst


def _move_aside(src: Path, run_dir: Path) -> Path:
  """Move a step directory to <run>/damaged_checkpoints/<step>[.N] (process 0; all wait)."""
  base = Path(run_dir) / "damaged_checkpoints" / src.name
  dst, n = base, 1
  while dst.exists():
    dst, n = base.with_name(f"{src.name}.{n}"), n + 1
  if jax.process_index() == 0:
    dst.parent.mkdir(parents=True, exist_ok=True)
    src.rename(dst)
  if jax.process_count() > 1:  # every process must see the move before orbax lists the steps again
    from jax.experimental import multihost_utils
    multihost_utils.sync_global_devices(f"skillplug_set_aside_{src.name}")
  return dst


def check_index(path: Path) -> None:
  """Check a checkpoint's OCDBT index without reading its arrays.

  Every B-tree node is decoded (checksummed), and every node and array value
  it points to must lie inside an existing file: a truncated or missing file
  is named here. Orbax reads all arrays at once; when several fail, the reads
  still in flight after its first error print hundreds of "Event loop is
  closed" tracebacks, which this check spares the common cases of. Orbax's
  JSON files beside the index (the step's _CHECKPOINT_METADATA, each item's
  _METADATA and _sharding) must parse, or are named as truncated too.
  """
  _check_json(path, Path(path) / "_CHECKPOINT_METADATA")
  for item in sorted(p for p in Path(path).iterdir() if p.is_dir()):
    if not (item / "manifest.ocdbt").exists():
      if any(item.glob("ocdbt.process_*")):
        raise DamagedCheckpoint(path, f"{item / 'manifest.ocdbt'} is missing")
      continue  # not an OCDBT item
    if not (item / "_METADATA").exists():  # orbax's tree of the arrays' names
      raise DamagedCheckpoint(path, f"{item / '_METADATA'} is missing")
    _check_json(path, item / "_METADATA")
    _check_json(path, item / "_sharding")
    try:
      base = ts.KvStore.open({"driver": "file", "path": f"{item.absolute()}/"}).result()
      versions = ts.ocdbt.dump(base).result().get("versions") or [{}]
      pending = [versions[-1].get("root", {}).get("location")]
      while pending:
        loc = pending.pop()
        if not isinstance(loc, str):
          continue
        _check_reference(path, item, loc)
        try:
          entries = ts.ocdbt.dump(base, loc).result().get("entries", [])
        except (ValueError, OSError) as e:  # name the file that holds the node
          file = _referenced_file(item, loc)
          if file is None:
            raise
          raise DamagedCheckpoint(path, f"{file} holds an index node that cannot be decoded "
                                        f"({short_reason(e)})") from e
        for entry in entries:
          if "location" in entry:  # a child node
            pending.append(entry["location"])
          elif "indirect_value" in entry:
            _check_reference(path, item, entry["indirect_value"])
    except DamagedCheckpoint:
      raise
    except (ValueError, OSError) as e:  # TensorStore: a node that cannot be read or decoded
      raise DamagedCheckpoint(path, short_reason(e)) from e


def check_checksums(path: Path) -> None:
  """Compare every file of each item of a checkpoint with the item's checksum manifest.

  A changed, truncated or missing file raises DamagedCheckpoint naming it; so does
  a missing manifest where the step metadata says `save` wrote one. Without
  either, the checkpoint predates checksums: it restores with orbax's checks
  alone, and a note says so. Reading the files costs about a second per GB.
  """
  unchecked = []
  for item in sorted(p for p in Path(path).iterdir() if p.is_dir()):
    if (item / CHECKSUMS).is_file():
      found = checksums.problems(item, CHECKSUMS)
      if found:
        (file, what), more = found[0], (f" (and {len(found) - 1} more files)" if len(found) > 1 else "")
        raise DamagedCheckpoint(path, f"{file} {what}{more}")
    elif _checksums_kept(path):
      raise DamagedCheckpoint(path, f"{item / CHECKSUMS} (its checksums) is missing")
    else:
      unchecked.append(item.name)
  if unchecked:
    print(f"note: checkpoint {path} has no checksums (written before they were kept); "
          "only orbax's own checks apply to it", file=sys.stderr)


def _checksums_kept(path: Path) -> bool:
  """Whether `save` wrote this checkpoint with checksums (its step metadata says so)."""
  try:
    meta = json.loads((Path(path) / "_CHECKPOINT_METADATA").read_bytes())
  except (OSError, ValueError):  # no step metadata: check_index has passed it, so an older orbax
    return False
  return isinstance(meta, dict) and _KEPT in (meta.get("custom_metadata") or {})


def _check_json(path: Path, file: Path) -> None:
  """`file`, where it exists, must be whole JSON (orbax writes these files whole)."""
  if not file.is_file():
    return
  try:
    json.loads(file.read_bytes())
  except ValueError as e:  # JSONDecodeError and UnicodeDecodeError
    raise DamagedCheckpoint(path, f"{file} is truncated or corrupt (not valid JSON: {e})") from e


def _check_reference(path: Path, item: Path, ref: str) -> None:
  """'<kind>:<base>:<file>:<offset>:<length>' (OCDBT's dump) must lie inside <item>/<base><file>."""
  file = _referenced_file(item, ref)
  if file is None:
    return  # a form this check does not know: leave it to the restore
  parts = ref.split(":")
  if not file.is_file():
    raise DamagedCheckpoint(path, f"{file} is missing")
  size, needed = file.stat().st_size, int(parts[-2]) + int(parts[-1])
  if size < needed:
    raise DamagedCheckpoint(path, f"{file} is truncated ({size} bytes, its index needs {needed})")


def _referenced_file(item: Path, ref: str) -> Path | None:
  """The file an OCDBT location '<kind>:<base>:<file>:<offset>:<length>' points into (None: another form)."""
  parts = ref.split(":")
  if len(parts) < 5 or not (parts[-2].isdigit() and parts[-1].isdigit()):
    return None
  return item / parts[1] / ":".join(parts[2:-2])


def tree_misfit(abstract, stored) -> str:
  """The first difference between a target tree and a checkpoint's metadata ('' if none)."""
  want, have = ocp.tree.to_flat_dict(abstract), ocp.tree.to_flat_dict(stored)
  name = lambda key: ".".join(map(str, key))  # noqa: E731
  missing, extra = sorted(set(want) - set(have)), sorted(set(have) - set(want))
  if missing:
    return f"it lacks {len(missing)} of the model's arrays (the first is {name(missing[0])})"
  if extra:
    return f"it holds {len(extra)} arrays the model does not have (the first is {name(extra[0])})"
  for k in sorted(want):
    a, b = tuple(want[k].shape), tuple(getattr(have[k], "shape", None) or ())
    if a != b:
      return f"{name(k)} has shape {b} in the checkpoint, the model expects {a}"
  return ""


def innermost(e: BaseException) -> BaseException:
  while e.__cause__ is not None:
    e = e.__cause__
  return e


def short_reason(e: BaseException, limit: int = 300) -> str:
  """The root cause in one line, without TensorStore's spec dump."""
  root = innermost(e)
  lines = str(root).strip().splitlines()
  text = lines[0] if lines else ""
  for tail in (" [tensorstore_spec=", " [source locations="):
    text = text.split(tail)[0]
  text = f"{type(root).__name__}: {text}" if text else type(root).__name__
  return text if len(text) <= limit else text[:limit - 3] + "..."
