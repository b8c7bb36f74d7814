"""Batched environments: Brax's vmap and episode-limit wrappers, plus batch rendering.

MJX's Warp renderer needs the batch size when its context is made, so images
are rendered here, on the whole batch, after the vmapped physics step. A batch
split over several GPUs (`devices`) gets one render context per GPU; Warp has
a single CPU device, so on a CPU the shards would share one context and race.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
from brax.envs.wrappers.training import EpisodeWrapper, VmapWrapper
from mujoco import mjx

from envs import appearance as appearances
from envs.env import TabletopEnv
from envs.robot import CAMERAS

RENDERER = "warp-raycast"  # what datasets and runs record (the C backend's is "mujoco-opengl")


class BatchedEnv:
  """The MJX-Warp backend. `num_envs` copies of a task: reset(keys[B]) and step(state, actions[B, 7]).

  With `render=True`, obs also holds `side_rgb` and `wrist_rgb` (uint8,
  [B, H, W, 3], `image_size` = (H, W)) from `mjx.render`; otherwise no image
  is made (state-only mode). appearance="shifted" draws each environment in
  its own look (`envs.appearance`, from its reset key, kept in
  state.info["appearance"]) through the batched model fields Warp's renderer
  reads per world; the physics is the same.
  """

  backend = "mjx-warp"

  def __init__(self, env: TabletopEnv, num_envs: int, render: bool = False, image_size=(64, 64),
               devices: tuple | None = None, appearance: str = "default"):
    if env.config.backend != "mjx-warp":
      raise ValueError(f"BatchedEnv runs MJX-Warp; the environment was made for {env.config.backend!r}")
    self.env = env
    self.renderer = RENDERER if render else None
    self.devices = devices  # JAX devices a sharded rendering batch runs on (num_envs each)
    self.num_envs = num_envs
    self.render = render
    self.render_s = None  # drawn inside the jitted step with the physics: not timed apart
    self.image_size = tuple(image_size)
    self.appearance = appearances.check(appearance)
    self._looks = appearances.looks_fn(env.mj_model) if render and appearance == "shifted" else None
    self._env = VmapWrapper(EpisodeWrapper(env, env.episode_length, action_repeat=1))
    self._ctx = None
    if render:
      m = env.mj_model
      self._cam_ids = [m.camera(c).id for c in CAMERAS]
      h, w = self.image_size
      warp_devices = None
      if devices is not None and len(devices) > 1:
        if any(d.platform != "gpu" for d in devices):
          raise ValueError("a rendering batch can be split over GPUs only (Warp has one CPU device, "
                           "so CPU shards would share one render context)")
        warp_devices = [f"cuda:{d.local_hardware_id}" for d in devices]
      self._ctx = mjx.create_render_context(  # Warp's cam_res is (W, H)
          m, nworld=num_envs, devices=warp_devices, cam_res=(w, h), use_textures=False, use_shadows=False,
          render_rgb=[True] * m.ncam, render_depth=[False] * m.ncam)

  @property
  def episode_length(self) -> int:
    return self.env.episode_length

  def reset(self, keys: jax.Array):
    if keys.shape[0] != self.num_envs:
      raise ValueError(f"got {keys.shape[0]} reset keys for {self.num_envs} environments")
    state = self._env.reset(keys)
    if self._looks is not None:
      state = state.replace(info={**state.info, "appearance": self._looks(keys)})
    return self._with_images(state)

  def step(self, state, actions: jax.Array):
    if actions.shape != (self.num_envs, self.env.action_size):
      raise ValueError(
          f"{self.env.name}: actions have shape {actions.shape}, expected "
          f"({self.num_envs}, {self.env.action_size})")
    if self.render:  # the per-env step knows nothing of images: drop them, render anew
      state = state.replace(obs={k: v for k, v in state.obs.items() if not k.endswith("_rgb")})
    return self._with_images(self._env.step(state, actions))

  def _with_images(self, state):
    if not self.render:
      return state
    mx = self.env.mjx_model
    ctx = self._ctx.pytree()

    def one(m, d):
      d = mjx.refit_bvh(mx, d, ctx)
      rgb, _, d = mjx.render(m, d, ctx)
      return rgb, d

    looks = state.info.get("appearance")
    if looks is None:
      rgb, data = jax.vmap(functools.partial(one, mx))(state.pipeline_state)
    else:  # the look's fields batched over worlds, the rest of the model shared
      axes = jax.tree.map(lambda _: None, mx).tree_replace({f: 0 for f in looks})
      rgb, data = jax.vmap(one, in_axes=(axes, 0))(mx.tree_replace(looks), state.pipeline_state)
    obs = dict(state.obs)
    for cam, cid in zip(CAMERAS, self._cam_ids):
      img = mjx.get_rgb(ctx, cid, rgb)
      obs[f"{cam}_rgb"] = (jnp.clip(img, 0.0, 1.0) * 255).astype(jnp.uint8)
    return state.replace(pipeline_state=data, obs=obs)
