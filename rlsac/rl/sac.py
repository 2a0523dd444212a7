"""SAC-Discrete (Christodoulou 2019) for choosing minimal sets, in the spirit of cleanrl's single file.

The action is a set of m points drawn from one softmax over the N points. We treat it as m draws of
a per-point policy pi(i | s):
  * critic: per-point values q_i(s); Q(s, a) = mean of q_i over the m points of a, so the twin
    critics regress the reward of a set and stay comparable across m;
  * soft value: V(s) = sum_i pi_i (min(q1_i, q2_i) - alpha log pi_i), the expectation of Q under one
    draw, with the per-point entropy standing in for the set's entropy (which is about m times it;
    the factor is absorbed into alpha);
  * actor: minimise sum_i pi_i (alpha log pi_i - min q_i); temperature: alpha is tuned so that the
    per-point entropy tracks ``target_entropy_scale * log(N_valid)``.
Transitions store only the instance index and the 3 memory channels: the data features are looked
up again when a batch is drawn, so a 100k buffer of 150 x 264 states fits in a few hundred MB.
"""

from __future__ import annotations

import copy
import time
from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F

from rlsac.errors import RlsacError
from rlsac.progress import tqdm  # no bars unless a person watches (not under CI, not redirected)
from rlsac.rl.env import MEMORY_DIM, EnvConf, SampleConsensusEnv
from rlsac.rl.policy import Actor, Critic, PolicyConf


@dataclass
class SACConf:
    total_steps: int = 3000  # vector-env steps (each steps ``num_envs`` episodes at once)
    num_envs: int = 64  # instances rolled out in parallel, one episode each (paper: one per pair)
    buffer_size: int = 100_000  # transitions kept
    batch_size: int = 128  # transitions per gradient update
    learning_starts: int = 2000  # transitions collected before the first update
    updates_per_step: int = 1  # gradient updates per vector-env step
    gamma: float = 0.9  # episodes last <= 15 steps; an effective horizon of ~10 matches that
    tau: float = 0.01  # polyak averaging of the target critics
    actor_lr: float = 3e-4  # Adam defaults of SAC
    critic_lr: float = 3e-4
    alpha_lr: float = 1e-3  # the temperature must move within a few thousand updates
    init_alpha: float = 0.01  # rewards are inlier ratios in [0, 1]: alpha = 1 would drown them in entropy
    target_entropy_scale: float = 0.5  # per-point entropy target = 0.5 log N: ~sqrt(N) plausible points
    train_sampling: str = "prob"  # probabilistic sampling while training (paper); "max" for the ablation

    # False: the psi cut ends the Bellman backup (the paper's fixed-length episode); True: it is a time
    # limit the state does not show, so bootstrap through it (cleanrl's truncation); kappa/varsigma stay terminal
    bootstrap_truncation: bool = False
    # Not in the paper (off = paper): the first warm_start_updates updates fit the actor to the ground-truth
    # inlier labels (cross-entropy, NG-RANSAC's initialisation) instead of the SAC actor loss; critics and
    # temperature learn as usual meanwhile. Gives SAC a sampler that already prefers inliers to refine.
    warm_start_updates: int = 0

    # checked by rlsac.config.build for every source (params.yaml, --set)
    ranges = {"total_steps": "[1, inf)", "num_envs": "[1, inf)", "buffer_size": "[1, inf)", "batch_size": "[1, inf)",
              "learning_starts": "[0, inf)", "updates_per_step": "[1, inf)", "gamma": "[0, 1]", "tau": "(0, 1]",
              "actor_lr": "(0, inf)", "critic_lr": "(0, inf)", "alpha_lr": "(0, inf)", "init_alpha": "(0, inf)",
              "target_entropy_scale": "[0, inf)", "train_sampling": ("prob", "max"),
              "warm_start_updates": "[0, inf)"}

    def __post_init__(self) -> None:
        sizes = (self.batch_size, self.buffer_size)
        if all(isinstance(v, int) for v in sizes) and self.batch_size > self.buffer_size:
            raise RlsacError(f"sac.batch_size {self.batch_size} is larger than sac.buffer_size {self.buffer_size} "
                             "(an update's batch is drawn from the buffer)")


class ReplayBuffer:
    """``extra``: width of a per-transition record of what the episode drew (rlsac.rl.episodes.RedrawnPairs: the point
    indices and the swap flag); 0 for fixed pairs, whose instance index says everything."""

    def __init__(self, size: int, n: int, m: int, device: torch.device, extra: int = 0):
        self.size, self.ptr, self.full = size, 0, False
        self.keys = ("inst", "mem", "mem2", "action", "reward", "done") + (("extra",) if extra else ())
        if extra:
            self.extra = torch.zeros((size, extra), dtype=torch.int16, device=device)
        self.inst = torch.zeros(size, dtype=torch.long, device=device)
        self.mem = torch.zeros((size, n, MEMORY_DIM), dtype=torch.float16, device=device)
        self.mem2 = torch.zeros((size, n, MEMORY_DIM), dtype=torch.float16, device=device)
        self.action = torch.zeros((size, m), dtype=torch.long, device=device)
        self.reward = torch.zeros(size, device=device)
        self.done = torch.zeros(size, device=device)

    def __len__(self) -> int:
        return self.size if self.full else self.ptr

    def add(self, inst, mem, mem2, action, reward, done, extra=None) -> None:
        k = inst.shape[0]
        idx = (self.ptr + torch.arange(k, device=inst.device)) % self.size
        self.inst[idx], self.mem[idx], self.mem2[idx] = inst, mem.half(), mem2.half()
        if extra is not None:
            self.extra[idx] = extra.to(torch.int16)
        self.action[idx], self.reward[idx], self.done[idx] = action, reward, done.float()
        self.full = self.full or self.ptr + k >= self.size
        self.ptr = (self.ptr + k) % self.size

    def state_dict(self) -> dict:
        """The filled part of the buffer (for an exact ``--resume``), on the CPU. Copies: torch.save of a slice
        writes the slice's whole storage (the 100k-row buffer for a few hundred transitions)."""
        n = len(self)
        return {"size": self.size, "ptr": self.ptr, "full": self.full,
                **{k: getattr(self, k)[:n].cpu().clone() for k in self.keys}}

    def load_state_dict(self, st: dict) -> None:
        n = st["inst"].shape[0]
        if st["size"] != self.size or tuple(st["mem"].shape[1:]) != tuple(self.mem.shape[1:]) or \
                tuple(st["action"].shape[1:]) != tuple(self.action.shape[1:]):
            raise ValueError(f"saved buffer {st['size']} x {tuple(st['mem'].shape[1:])} does not fit "
                             f"{self.size} x {tuple(self.mem.shape[1:])}")
        if ("extra" in st) != ("extra" in self.keys):
            raise ValueError("saved buffer and this training disagree on redrawn episodes (episodes.pool)")
        for k in self.keys:
            getattr(self, k)[:n] = st[k].to(self.inst.device)
        self.ptr, self.full = int(st["ptr"]), bool(st["full"])

    def sample(self, k: int, generator: torch.Generator):
        """-> inst, mem, mem2, action, reward, done and the episode records (None for fixed pairs) of k transitions."""
        idx = torch.randint(len(self), (k,), generator=generator, device=generator.device).to(self.inst.device)
        extra = self.extra[idx].long() if "extra" in self.keys else None
        return (self.inst[idx], self.mem[idx].float(), self.mem2[idx].float(), self.action[idx],
                self.reward[idx], self.done[idx], extra)


def masked_policy(logits: torch.Tensor, mask: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """-> probabilities and log-probabilities (R, N), both exactly 0 on masked points."""
    logp = torch.log_softmax(logits, dim=-1).masked_fill(~mask, 0.0)
    return logp.exp() * mask, logp


class SACAgent(torch.nn.Module):
    def __init__(self, in_channels: int, pconf: PolicyConf, conf: SACConf):
        super().__init__()
        self.conf = conf
        self.actor = Actor(in_channels, pconf)
        self.qf1, self.qf2 = Critic(in_channels, pconf), Critic(in_channels, pconf)
        self.qf1_target, self.qf2_target = copy.deepcopy(self.qf1), copy.deepcopy(self.qf2)
        for p in [*self.qf1_target.parameters(), *self.qf2_target.parameters()]:
            p.requires_grad_(False)
        self.log_alpha = torch.nn.Parameter(torch.tensor(float(np.log(conf.init_alpha))))
        self.q_opt = torch.optim.Adam([*self.qf1.parameters(), *self.qf2.parameters()], lr=conf.critic_lr)
        self.actor_opt = torch.optim.Adam(self.actor.parameters(), lr=conf.actor_lr)
        self.alpha_opt = torch.optim.Adam([self.log_alpha], lr=conf.alpha_lr)
        self.register_buffer("n_updates", torch.zeros((), dtype=torch.long))  # saved with the state: resume-safe

    def set_kernels(self, name: str, neighbour_max: str = "eager") -> SACAgent:
        """Every network's training-path products from kernels ``name`` (rlsac.rl.kernels): ATen's, the record's, or
        oneDNN's (the same function, faster under the portable pins, other last bits); and its neighbour max, eager
        (the record's) or compiled (the same bytes, faster)."""
        for net in (self.actor, self.qf1, self.qf2, self.qf1_target, self.qf2_target):
            net.set_kernels(name, neighbour_max)
        return self

    def update(self, s, s2, mask, graph, action, reward, done, labels=None) -> dict[str, float]:
        """One gradient step of critics, actor and temperature on a batch of transitions.

        s, s2 (b, N, C) states; mask (b, N); graph (b, N, k) their shared kNN graph; action (b, m).
        labels (b, N) bool ground-truth inliers: given, the actor step is the supervised warm start.
        """
        c, alpha = self.conf, self.log_alpha.exp().detach()
        # --- critics: soft Bellman target from the next state's policy and the target critics
        with torch.no_grad():
            p2, logp2 = masked_policy(self.actor(s2, mask, graph), mask)
            q2 = torch.minimum(self.qf1_target(s2, mask, graph), self.qf2_target(s2, mask, graph))
            q2 = q2.masked_fill(~mask, 0.0)
            v2 = (p2 * (q2 - alpha * logp2)).sum(-1)
            target = reward + c.gamma * (1.0 - done) * v2
        q1_all, q2_all = self.qf1(s, mask, graph), self.qf2(s, mask, graph)
        q1_a = q1_all.gather(1, action).mean(-1)
        q2_a = q2_all.gather(1, action).mean(-1)
        qf_loss = F.mse_loss(q1_a, target) + F.mse_loss(q2_a, target)
        self.q_opt.zero_grad()
        qf_loss.backward()
        self.q_opt.step()

        # --- actor: expected soft advantage under the current per-point policy
        p, logp = masked_policy(self.actor(s, mask, graph), mask)
        qmin = torch.minimum(q1_all, q2_all).detach().masked_fill(~mask, 0.0)
        if labels is None:
            actor_loss = (p * (alpha * logp - qmin)).sum(-1).mean()
        else:  # cross-entropy against the uniform distribution over the true inliers (rows without any skipped)
            y = labels.float() * mask
            n_in = y.sum(-1)
            actor_loss = -((y * logp).sum(-1) / n_in.clamp_min(1.0))[n_in > 0].sum() / n_in.gt(0).sum().clamp_min(1)
        self.actor_opt.zero_grad()
        actor_loss.backward()
        self.actor_opt.step()

        # --- temperature: keep the per-point entropy near its target
        entropy = -(p * logp).sum(-1).detach()
        target_h = c.target_entropy_scale * torch.log(mask.sum(-1).float())
        alpha_loss = (self.log_alpha.exp() * (entropy - target_h)).mean()
        self.alpha_opt.zero_grad()
        alpha_loss.backward()
        self.alpha_opt.step()

        self.n_updates += 1
        with torch.no_grad():
            for net, tgt in ((self.qf1, self.qf1_target), (self.qf2, self.qf2_target)):
                for p_, tp in zip(net.parameters(), tgt.parameters(), strict=True):
                    tp.lerp_(p_, c.tau)
        return {
            "losses/qf1": F.mse_loss(q1_a, target).item(), "losses/qf2": F.mse_loss(q2_a, target).item(),
            "losses/qf1_values": q1_a.mean().item(), "losses/actor": actor_loss.item(),
            "losses/alpha": alpha_loss.item(), "charts/alpha": alpha.item(), "charts/entropy": entropy.mean().item(),
        }


def train_loop(agent: SACAgent, task, data: dict, env_conf: EnvConf, start_step: int, generator: torch.Generator,
               log, validate=None, val_every: int = 500, checkpoint=None, ckpt_every: int = 500,
               buffer: ReplayBuffer | None = None, stop=None, episodes=None, on_step=None) -> ReplayBuffer:
    """Collect episodes with the actor and update the agent; ``data`` = coords, mask, features (I, ...).

    ``log(metrics, step)``, ``validate(step) -> metrics``, ``checkpoint(step, buffer)`` (at the first episode
    end at or after every ``ckpt_every`` steps) and ``stop() -> bool`` (checked after each step; the loop
    checkpoints and returns at the next episode end) are callbacks; ``buffer`` resumes a saved buffer.
    """
    from rlsac.rl.episodes import FixedPairs

    c = agent.conf
    source = episodes if episodes is not None else FixedPairs(task, data, agent.actor)
    I, N = source.n_instances, source.n_points
    device = data["mask"].device
    if buffer is None:
        buffer = ReplayBuffer(c.buffer_size, N, task.sample_size, device, extra=source.extra_width)
    env = SampleConsensusEnv(task, env_conf, training=True)
    running, t0, n_trans, n_upd, ckpt_due = False, time.time(), 0, 0, False
    ep_return = torch.zeros(c.num_envs, device=device)
    bar = tqdm(range(start_step, c.total_steps), desc="train", unit="step", dynamic_ncols=True,
               initial=start_step, total=c.total_steps)
    for step in bar:
        if not running:
            inst = torch.randint(I, (c.num_envs,), generator=generator, device=generator.device).to(device)
            batch, feats, graph, drawn = source.draw(inst, generator)
            state = env.reset(batch, feats, episodes=1, generator=generator)
            ep_return.zero_()
            running = True
        with torch.no_grad():
            logits = agent.actor(state, env.mask, graph)
        idx = env.select(logits, sample=c.train_sampling == "prob")
        mem = env.memory()
        reward, done, act = env.step(idx)
        if c.bootstrap_truncation:  # stored done = the kappa/varsigma stops only, not the psi cut
            done = done & ((env.same_count >= env_conf.kappa) | (env.no_better >= env_conf.varsigma))
        state = env.state()
        buffer.add(inst[act], mem[act], env.memory()[act], idx[act], reward[act], done[act],
                   None if drawn is None else drawn[act])
        n_trans += int(act.sum())
        ep_return += reward
        if not env.active.any():
            running = False
            log({"charts/episode_return": ep_return.mean().item(),
                 "charts/episode_length": env.t - 1,
                 "charts/inlier_ratio": (env.best_count.float() / batch["mask"].sum(-1)).mean().item()}, step)
        if len(buffer) >= c.learning_starts:
            for _ in range(c.updates_per_step):
                b_inst, b_mem, b_mem2, b_a, b_r, b_d, b_extra = buffer.sample(c.batch_size, generator)
                x, m, b_graph = source.lookup(b_inst, b_extra)
                # ground-truth inliers, only for the supervised warm start (the source's labels, if it has any)
                warm = source.has_labels and int(agent.n_updates) < c.warm_start_updates
                metrics = agent.update(torch.cat([x, b_mem], -1), torch.cat([x, b_mem2], -1), m,
                                       b_graph, b_a, b_r, b_d, source.labels(b_inst, b_extra) if warm else None)
                metrics["charts/warm_start"] = float(warm)
                n_upd += 1
            if step % 50 == 0:
                el = max(time.time() - t0, 1e-9)
                metrics.update({"charts/transitions_per_s": n_trans / el, "charts/updates_per_s": n_upd / el})
                log(metrics, step)
                bar.set_postfix(alpha=f"{metrics['charts/alpha']:.3f}", H=f"{metrics['charts/entropy']:.2f}")
        if on_step is not None:
            on_step(step + 1)
        if validate is not None and (step + 1) % val_every == 0:
            log(validate(step + 1), step)
        # A checkpoint waits for the end of the running episode: the loop's whole state is then the agent, the
        # buffer and the generator, so resuming from it replays the uninterrupted run exactly. ``stop()`` (a
        # signal) ends the loop the same way, after a checkpoint.
        ckpt_due = ckpt_due or (checkpoint is not None and (step + 1) % ckpt_every == 0)
        stopping = stop is not None and stop()
        if (ckpt_due or stopping) and not running:
            if checkpoint is not None:
                checkpoint(step + 1, buffer)
            ckpt_due = False
            if stopping:
                break
    bar.close()
    return buffer


def seed_everything(seed: int) -> torch.Generator:
    np.random.seed(seed)
    torch.manual_seed(seed)
    return torch.Generator().manual_seed(seed)
