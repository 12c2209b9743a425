"""rama_dreamer.py with `torch.compile` on its RSSM loops: a version of the script for `bench_update.py --compare-to`,
to measure on a GPU whether fused kernels pay under --cuda-graph before a flag for them joins the scripts (issue 39).

Why: a graphed update is bound by its thousands of tiny kernels (docs/benchmarks.md: 21 ms for a state-mode update
on an H100, ~3 µs per kernel), most of them the element-wise tails of the RSSM's 65 steps and of their backward passes
(softplus, the sample, the gradient sums). Inductor fuses those tails into a few kernels around each matrix product.
Eagerly, compiling was slower (its guards cost more per call than the fusion saved); replayed from a CUDA graph, the
guards are not run at all, which is what this measures.

    python benchmarks/bench_update.py --device cuda --cuda-graph True --compare-to benchmarks/compiled_rssm.py \
        --sizes small --obs-type state --mlp-units 200 --methods dreamer rrama vrama --updates 20
    COMPILE=loops python benchmarks/bench_update.py ...     # the whole filter and imagination, unrolled

COMPILE=steps (the default) compiles the RSSM's step functions (deter_step and obs_step, the filter's; img_step,
imagination's): each is a small graph, compiled once per shape and reused by every step. COMPILE=loops compiles
RSSM.observe and `imagine` whole (50 and 15 steps unrolled: minutes to compile, and the gradient sums across steps
fuse too). COMPILED_SCRIPT=rama_metaworld.py compiles the sibling instead. Random draws stay torch's own (inductor's
`fallback_random`), so a compiled update draws the eager script's numbers and gives its losses up to rounding
(tests/test_speed.py::test_the_compiled_rssm_variant_gives_the_scripts_updates checks it on the CPU).
"""
import os

import torch

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
SCRIPT = os.path.join(ROOT, os.environ.get("COMPILED_SCRIPT", "rama_dreamer.py"))
MODE = os.environ.get("COMPILE", "steps")
if MODE not in ("steps", "loops"):
    raise SystemExit(f"COMPILE={MODE}: must be `steps` or `loops`")

with open(SCRIPT) as f:  # the script's own code, run in this module's namespace: a copy that the patches below
    exec(compile(f.read(), SCRIPT, "exec"))  # change without touching the script imported beside it # noqa: S102

torch._inductor.config.fallback_random = True  # torch's own random draws: the eager script's numbers
if MODE == "steps":
    for name in ("deter_step", "obs_step", "img_step"):  # RSSM: defined by the exec above
        setattr(RSSM, name, torch.compile(getattr(RSSM, name), dynamic=False))  # noqa: F821
else:
    RSSM.observe = torch.compile(RSSM.observe, dynamic=False)  # noqa: F821
    imagine = torch.compile(imagine, dynamic=False)  # noqa: F821
