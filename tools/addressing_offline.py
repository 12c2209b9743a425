"""Does f_φ learn its objective when the world model holds still? An offline check of a finished addressed run.

RRAMa's bandit (Eq. 2) is rewarded with the world model's predicted reward sum of the chunk it picks. In a real run
that reward moves while f_φ learns (the world model trains beside it). This tool takes a run's folder and holds its
final world model fixed, then trains f_φ on the run's own objective (Eq. 1, 2 or 3, by the run's --method) for
--updates updates, from two starting points:
    fresh  a newly initialised f_φ (one per --seeds): can this objective teach f_φ at all, and how fast?
    run    the run's own trained f_φ (address.pt, with its Adam state): can it still move where the signal points?
Every --eval-every updates it scores q̂(j | x) over the candidate chunks of M (as the batch mix uses it), for
--eval-rows current-task chunks x, against a uniform pick:
    predicted  E_q̂[predicted reward sum] - uniform's: the bandit's own objective, under the fixed world model
    stored     E_q̂[stored reward sum] - uniform's: the rewards written in the episodes (the prior task's own
               reward when M comes from another task)
    prior mass q̂'s mass on prior-run chunks (M also holds the run's own episodes)
    entropy    q̂'s entropy as a fraction of a uniform q̂'s
    ‖f(M_j)‖   the candidates' embedding norm, and logit s.d. the spread of f(x)ᵀ f(M_j) over them: how sharp q̂
               can be
    pinned     the share of f_φ's GRU update gates that are exactly 0 or 1 in float32 over a fixed sample of M's
               chunks (a pinned gate passes back no gradient), and grad norm the median gradient norm of f_φ over
               the updates since the last scoring: has f_φ stopped learning?
and prints a Markdown table of the mean over seeds with the 95% t-interval; --out writes the numbers as JSON.

Three knobs test why f_φ may not follow its objective; the defaults are the run's own f_φ (the paper's):
    --logit-scale s   multiply the logits f(x)ᵀ f(M_j) by s (1/√U is a transformer's scale): does q̂ saturate?
    --x-embedding frozen   embed x with a frozen copy of the starting f_φ (the training scripts'
                      --address-x-net frozen), so that a step of φ moves f(M_j) only (the paper's stop-gradient on
                      f(x) stops the gradient, yet the shared weights still move f(x)): does the shared embedding
                      pull q̂ toward chunks that look like x?
    --lr              f_φ's Adam learning rate instead of the run's --address-lr

M is rebuilt as the run built it at its end: the prior episodes (--prior-dirs, --prior-min-return, K drawn with the
run's seed) plus every episode the run collected; x comes from the (last) task's own episodes. Nothing in the run
folder is written. Runs of rama_dreamer.py and of rama_metaworld.py. CPU by default; a cartpole state run at batch
16 takes about 0.3 s per update on one core.

Run (from the repository root):
    python tools/addressing_offline.py runs/cartpole_tables/balance__rrama__s1/<run> --out results/x.json
    python tools/addressing_offline.py <run> --starts fresh --updates 600 --seeds 0 1 2 3 4
"""
import dataclasses
import json
import os
import sys
import time
from dataclasses import dataclass
from typing import Literal, Optional, Tuple

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, ROOT)  # the training script sits in the repository root

import numpy as np  # noqa: E402
import torch  # noqa: E402
import tyro  # noqa: E402

import rama_dreamer as rd  # noqa: E402
import rama_metaworld  # noqa: E402  (Meta-World itself is imported only when an env is made)


@dataclass
class Args:
    run: tyro.conf.Positional[str]
    """a run folder of an addressed method (vrama, rrama, rbrama) with its checkpoint.pt and address.pt"""
    starts: Tuple[Literal["fresh", "run"], ...] = ("fresh", "run")
    """f_φ's starting points: `fresh` (new weights, one per seed) and/or `run` (the run's trained f_φ)"""
    updates: int = 300
    """addressing updates per seed and start (the run made C per collected episode, 900 in a 10-episode run)"""
    eval_every: int = 50
    """score q̂ every this many updates (and before the first)"""
    seeds: Tuple[int, ...] = (0, 1, 2)
    """seeds of the fresh weights and of the chunk samplers"""
    eval_rows: int = 64
    """current-task chunks x that q̂ is scored for"""
    device: str = "cpu"
    """`cpu`, `cuda`, `auto`"""
    out: Optional[str] = None
    """write the table's numbers (every seed, every scoring) to this JSON file"""
    logit_scale: float = 1.0
    """multiply the logits f(x)ᵀ f(M_j) by this (1: the paper's plain dot product)"""
    x_embedding: Literal["shared", "frozen"] = "shared"
    """`shared`: x is embedded as the run did (by f_φ itself, the paper); `frozen`: by a frozen copy of the starting
    f_φ (for --starts run, the run's trained f_φ, or its own frozen copy if it had one)"""
    lr: Optional[float] = None
    """f_φ's learning rate (default: the run's --address-lr)"""


class VariantAddressing(rd.Addressing):
    """The script's Addressing with the logits scaled (through f(M_j), which D holds too)."""

    def __init__(self, obs_shape, action_size: int, run_args: rd.Args, device, logit_scale: float):
        super().__init__(obs_shape, action_size, run_args, device)
        self.logit_scale = logit_scale

    def embed(self, batch: dict):
        return self.logit_scale * super().embed(batch)  # (B, U): f(M_j), scaled


def load_weights(module: torch.nn.Module, state: dict, path: str):
    """load_state_dict, also for checkpoints written before the state encoder and decoder became plain modules
    (commit 6170a30: their layers were named `encoder.net.*`, `decoder.net.*`); one line naming the file otherwise."""
    try:
        module.load_state_dict(state)
    except RuntimeError:
        renamed = {k.replace("encoder.net.", "encoder.").replace("decoder.net.", "decoder."): v
                   for k, v in state.items()}
        rd.load_state(path, module, renamed)


def rebuild_buffers(args: rd.Args, run_path: str):
    """(M, the current task's own episodes, how many of M's episodes are prior ones, the observation shape, the action
    size, the current task's folder), as the run had them at its end."""
    folders = rd.episode_folders(run_path)  # one per task of a --task-sequence, in order
    if not folders:
        raise rd.UsageError(f"{run_path}: holds no episode files")
    first = rd.load_episode(rd.list_episode_files(folders[0])[0])
    obs_shape, action_size = first["obs"].shape[1:], first["action"].shape[1]
    multitask, own = rd.Replay(), rd.Replay()
    if args.prior_dirs:  # the run's main() draws these first from default_rng(seed): the same K episodes
        for episode in rd.load_prior_episodes(args.prior_dirs, args.prior_min_return, args.prior_max_episodes,
                                              obs_shape, action_size, np.random.default_rng(args.seed)):
            multitask.add(episode)
    num_prior = len(multitask)
    for folder in folders:
        for path in rd.list_episode_files(folder):
            episode = rd.load_episode(path)
            multitask.add(episode)
            if folder == folders[-1]:
                own.add(episode)
    return multitask, own, num_prior, obs_shape, action_size, os.path.dirname(folders[-1])


@torch.no_grad()
def candidate_rewards(agent, multitask, seq_len: int, cap: int, device):
    """The fixed candidate chunks of M that every scoring uses, with their stored and predicted reward sums."""
    episode_ids, starts = multitask.grid_ids(seq_len, cap, np.random.default_rng(0))
    stored = multitask.chunk_rewards(episode_ids, starts, seq_len)  # (N_c,)
    predicted = np.concatenate([  # (N_c,) the bandit's reward under the fixed world model
        rd.predicted_reward_sum(agent.wm, rd.to_torch(multitask.gather(episode_ids[i:i + 256], starts[i:i + 256],
                                                                       seq_len), device)).double().cpu().numpy()
        for i in range(0, len(starts), 256)])
    return episode_ids, stored, predicted


@torch.no_grad()
def score(addressing, multitask, x: dict, candidates, num_prior: int, seq_len: int, cap: int) -> dict:
    """q̂(j | x_i) over the fixed candidates against a uniform pick (the rows of x averaged)."""
    episode_ids, stored, predicted = candidates
    addressing.refresh(multitask, seq_len, cap, np.random.default_rng(0))  # D for the same candidates each time
    assert np.array_equal(addressing.candidates[0], episode_ids)
    embeddings = addressing.candidate_embeddings.double()  # (N_c, U): D, times the logit scale
    logits = (addressing.embed_x(x).double() @ embeddings.T).cpu()  # (rows, N_c), as Addressing.probs
    q = logits.softmax(-1).numpy()  # (rows, N_c)
    entropy = -(q * logits.log_softmax(-1).numpy()).sum(-1)  # (rows,)
    return {"predicted": float((q @ predicted).mean() - predicted.mean()),
            "stored": float((q @ stored).mean() - stored.mean()),
            "prior_mass": float((q @ (episode_ids < num_prior)).mean()),
            "entropy": float(entropy.mean() / np.log(q.shape[1])),
            "embedding_norm": float(embeddings.norm(dim=-1).mean() / addressing.logit_scale),  # ‖f(M_j)‖
            "logit_sd": float(logits.numpy().std(-1).mean())}  # the spread of f(x_i)ᵀ D_j over the candidates


@torch.no_grad()
def pinned_gates(net: rd.AddressNet, batch: dict) -> float:
    """The share of f_φ's GRU update gates z that are exactly 0 or 1 in float32 over a batch of chunks. The GRU
    steps h_t = (1 − z)·n_t + z·h_(t−1) as torch's nn.GRU does (gates in the order reset, update, candidate); where z
    is pinned, no gradient passes, and a unit with z = 1 keeps its state to the chunk's end."""
    fed = []  # what AddressNet.forward feeds its GRU, caught on the way in
    hook = net.gru.register_forward_hook(lambda module, args, output: fed.append(args[0]))
    net(batch["obs"], batch["action"], batch["reward"])
    hook.remove()
    inputs, gru, units = fed[0], net.gru, net.gru.hidden_size  # inputs: (B, T, U)
    state = inputs.new_zeros(len(inputs), units)  # (B, U)
    pinned = []
    for t in range(inputs.shape[1]):
        from_input = inputs[:, t] @ gru.weight_ih_l0.T + gru.bias_ih_l0  # (B, 3U)
        from_state = state @ gru.weight_hh_l0.T + gru.bias_hh_l0  # (B, 3U)
        reset = torch.sigmoid(from_input[:, :units] + from_state[:, :units])
        update = torch.sigmoid(from_input[:, units:2 * units] + from_state[:, units:2 * units])
        candidate = torch.tanh(from_input[:, 2 * units:] + reset * from_state[:, 2 * units:])
        state = (1 - update) * candidate + update * state
        pinned.append(((update == 0) | (update == 1)).float().mean())
    return float(torch.stack(pinned).mean())


def mean_ci(values) -> str:
    """mean [95% t-interval] over seeds (the mean alone for one seed)."""
    values = np.asarray(values, float)
    if len(values) < 2:
        return f"{values.mean():+.1f}"
    from scipy import stats

    half = stats.t.ppf(0.975, len(values) - 1) * values.std(ddof=1) / np.sqrt(len(values))
    return f"{values.mean():+.1f} [{values.mean() - half:+.1f}, {values.mean() + half:+.1f}]"


def saved_by(run: str):
    """The training script that wrote the run, by its env id as tools/eval_actions.py tells it. Only the run's args
    differ between the two; what this tool uses past them is their shared text."""
    try:
        with open(os.path.join(run, "args.json")) as f:
            return rama_metaworld if json.load(f)["env_id"].startswith("metaworld/") else rd
    except (OSError, ValueError, LookupError, TypeError, AttributeError):
        return rd  # resolve_run names what is wrong with the folder


def main(cli: Args):
    script = saved_by(cli.run)
    try:  # the run's saved args, checked as --resume checks them
        run_args, run_path = script.resolve_run(script.Args(resume=cli.run), set())
    except script.UsageError as e:  # its messages name --resume, which this tool does not have
        raise rd.UsageError(str(e).replace("--resume ", "", 1)) from None
    if run_args.method not in rd.ADDRESSED_METHODS:
        raise rd.UsageError(f"{cli.run}: a {run_args.method} run has no f_φ (needs vrama, rrama or rbrama)")
    if cli.updates < 0 or cli.eval_every < 1 or cli.eval_rows < 1 or not cli.seeds or not cli.starts:
        raise rd.UsageError("--updates must be >= 0, --eval-every and --eval-rows >= 1, --seeds and --starts non-empty")
    if cli.logit_scale <= 0 or (cli.lr is not None and cli.lr <= 0):
        raise rd.UsageError("--logit-scale and --lr must be > 0")
    device = rd.resolve_device(cli.device)
    lr = cli.lr or run_args.address_lr
    address_args = dataclasses.replace(run_args, address_x_net="frozen") if cli.x_embedding == "frozen" else run_args
    multitask, own, num_prior, obs_shape, action_size, task_path = rebuild_buffers(run_args, run_path)
    checkpoint = rd.read_checkpoint(os.path.join(task_path, "checkpoint.pt"), run_args)
    saved_address = rd.read_checkpoint(os.path.join(run_path, "address.pt"), run_args)
    if checkpoint is None or saved_address is None:
        raise rd.UsageError(f"{cli.run}: needs checkpoint.pt and address.pt (a run that finished at least one round)")
    agent = rd.Agent(obs_shape, action_size, run_args).to(device)
    load_weights(agent, checkpoint["agent"], os.path.join(task_path, "checkpoint.pt"))
    candidates = candidate_rewards(agent, multitask, run_args.seq_len, run_args.address_candidates, device)
    x_eval = rd.to_torch(own.sample(cli.eval_rows, run_args.seq_len, np.random.default_rng(12345)), device)
    m_eval = rd.to_torch(multitask.sample(cli.eval_rows, run_args.seq_len, np.random.default_rng(54321)), device)
    print(f"{cli.run}: {run_args.method}, M = {num_prior} prior + {len(multitask) - num_prior} own episodes, "
          f"{cli.updates} updates x {len(cli.seeds)} seeds per start, {device}; logit scale {cli.logit_scale:g}, "
          f"x embedded by {'a frozen copy of f_φ' if cli.x_embedding == 'frozen' else 'f_φ'}, "
          f"lr {lr:g}", flush=True)

    rows = []  # one per (start, seed, scoring)
    for start in cli.starts:
        for seed in cli.seeds:
            torch.manual_seed(seed)
            rng = np.random.default_rng(seed)
            addressing = VariantAddressing(obs_shape, action_size, address_args, device, cli.logit_scale)
            if start == "run":
                load_weights(addressing.net, saved_address["net"], os.path.join(run_path, "address.pt"))
                if addressing.x_net is not addressing.net:  # frozen: the run's own copy, or else its trained f_φ
                    load_weights(addressing.x_net, saved_address.get("x_net", saved_address["net"]),
                                 os.path.join(run_path, "address.pt"))
                addressing.opt.load_state_dict(saved_address["opt"])
            for group in addressing.opt.param_groups:
                group["lr"] = lr
            t0, grad_norms = time.perf_counter(), []  # grad_norms: those of the updates since the last scoring
            for update in range(cli.updates + 1):
                if update % cli.eval_every == 0 or update == cli.updates:
                    rows.append({"start": start, "seed": seed, "update": update,
                                 **score(addressing, multitask, x_eval, candidates, num_prior, run_args.seq_len,
                                         run_args.address_candidates),
                                 "pinned": pinned_gates(addressing.net, m_eval),
                                 "grad_norm": float(np.median(grad_norms)) if grad_norms else float("nan")})
                    grad_norms = []
                if update < cli.updates:  # x ~ M_τ, M_j ~ M, one step of φ with the agent fixed
                    x = rd.to_torch(own.sample(run_args.batch_size, run_args.seq_len, rng), device)
                    m_batch = rd.to_torch(multitask.sample(run_args.address_batch, run_args.seq_len, rng), device)
                    grad_norms.append(float(addressing.train(agent, x, m_batch, run_args)["addressing/grad_norm"]))
            print(f"  {start} seed {seed}: {cli.updates} updates in {time.perf_counter() - t0:.0f} s, predicted-reward "
                  f"gain {rows[-1]['predicted']:+.1f}", flush=True)

    episode_ids, stored, predicted = candidates
    facts = {"candidates": len(stored), "prior_share": float((episode_ids < num_prior).mean()),
             "reward_corr": float(np.corrcoef(predicted, stored)[0, 1]) if stored.std() > 0 else float("nan")}
    print(f"\nq̂ against a uniform pick, mean over {len(cli.seeds)} seeds [95% t-interval]; over the "
          f"{facts['candidates']} candidates the world model's predicted and the stored chunk rewards correlate at "
          f"{facts['reward_corr']:.2f}, and {facts['prior_share']:.2f} of them come from prior runs\n")
    print("| start | update | predicted-reward gain | stored-reward gain | prior mass | entropy / uniform "
          "| ‖f(M_j)‖ | logit s.d. | pinned gates | grad norm |")
    print("|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|")
    for start in cli.starts:
        for update in sorted({r["update"] for r in rows}):
            sel = [r for r in rows if r["start"] == start and r["update"] == update]
            grad_norm = [r["grad_norm"] for r in sel]  # nan at update 0: no updates yet
            print(f"| {start} | {update} | {mean_ci([r['predicted'] for r in sel])} | "
                  f"{mean_ci([r['stored'] for r in sel])} | {np.mean([r['prior_mass'] for r in sel]):.2f} | "
                  f"{np.mean([r['entropy'] for r in sel]):.2f} | {np.mean([r['embedding_norm'] for r in sel]):.1f} | "
                  f"{np.mean([r['logit_sd'] for r in sel]):.1f} | {np.mean([r['pinned'] for r in sel]):.2f} | "
                  f"{'–' if np.isnan(grad_norm).all() else f'{np.mean(grad_norm):.3g}'} |")
    if cli.out:
        os.makedirs(os.path.dirname(os.path.abspath(cli.out)), exist_ok=True)
        with open(cli.out, "w") as f:
            json.dump({"run": cli.run, "args": dataclasses.asdict(cli), "method": run_args.method, **facts,
                       "rows": rows}, f, indent=1)
        print(f"\nwrote {cli.out}")


if __name__ == "__main__":
    try:
        main(tyro.cli(Args))
    except rd.UsageError as e:
        print(f"error: {e}", file=sys.stderr)
        sys.exit(e.code)
