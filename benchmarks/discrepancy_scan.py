"""Profile the discrepancy workflow's 3D residual over one parameter of one candidate effect.

    python -m benchmarks.discrepancy_scan --run RUN --data MEASURED --effect table_friction --param mu \
        --values=-0.3,0,0.16,0.27,0.5      # (= when the first value is negative)

    python -m benchmarks.discrepancy_scan --run RUN --data MEASURED --scale-term robot --values 1,0.6,0.3

For every value (a number, or a JSON list for a vector parameter: ``--values "[0,2,0];[0,5,0]"`` with
``;`` between values) the model with the effect added as a direct term at that value (or, with
``--scale-term KEY``, with the force of its own term KEY multiplied by the value: ``robot`` at 0.6 is
a grip that transmits 60% of what the model learned) is rolled out open loop on every episode, and
the mean 3D residual (observed object point -> nearest splat, m) is printed per episode and overall,
with the workflow config's frames, points and passive-object rule. It tells whether a missed effect
is a fitting failure (the residual has a lower minimum elsewhere) or a model that cannot express it
(it has not).
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m benchmarks.discrepancy_scan", description=__doc__.splitlines()[0])
    p.add_argument("--run", required=True, metavar="RUN", help="soma train run folder")
    p.add_argument("--data", required=True, metavar="MEASURED")
    p.add_argument("--effect", default=None, help="registered effect name (added as a direct term)")
    p.add_argument("--param", default=None, help="its learnable parameter")
    p.add_argument("--scale-term", default=None, metavar="KEY",
                   help="instead of --effect/--param: scale the force of the model's own term KEY (e.g. robot)")
    p.add_argument("--values", required=True, help="comma-separated numbers, or ';'-separated JSON lists")
    p.add_argument("--config", default="default", metavar="NAME|YAML", help="workflow config (frames, points, passive rule)")
    p.add_argument("--split", default=None, help="only the episodes of this manifest split")
    args = p.parse_args(argv)
    if (args.scale_term is None) == (args.effect is None or args.param is None):
        p.error("give either --effect and --param, or --scale-term")
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    import numpy as np
    import torch

    torch.set_num_threads(int(os.environ.get("OMP_NUM_THREADS", "1") or 1))
    from trainer.config import load_train_config
    from trainer.discrepancy import episode_obs, load_discrepancy_config, load_model, residual_per_frame
    from trainer.evaluate import EvalContext

    values = [json.loads(v) for v in (args.values.split(";") if ";" in args.values else args.values.split(","))]
    run = Path(args.run)
    cfg = load_discrepancy_config(args.config)
    ctx = EvalContext(args.data, load_train_config(run / "train_config.yaml"), run / "scene")
    sim = load_model(run / "checkpoint.pt", cfg)
    refs = [r for r in ctx.refs if args.split is None or r.split == args.split]
    if not refs:
        print(f"discrepancy_scan: error: no episodes (split {args.split})", file=sys.stderr)
        return 2
    obs = [episode_obs(ctx, r, cfg)[0] for r in refs]
    if args.scale_term is not None:
        if args.scale_term not in sim.effects.terms:
            print(f"discrepancy_scan: error: the model has no term {args.scale_term!r} "
                  f"(has {', '.join(sim.effects.terms)})", file=sys.stderr)
            return 2
        factor = torch.ones(())
        sim.effects.terms[args.scale_term].register_forward_hook(lambda mod, inp, out: out * factor)
        name = f"{args.scale_term}_scale"
    else:
        sim.add_effect({"name": args.effect, "direct": True, "fitted_after_training": True})
        params = dict(sim.effects[args.effect].named_parameters())
        if args.param not in params:
            print(f"discrepancy_scan: error: {args.effect} has no parameter {args.param!r} (has {', '.join(params)})",
                  file=sys.stderr)
            return 2
        prm, name = params[args.param], args.param
    print(f"run {run}, data {args.data}, {len(obs)} episodes; mean 3D residual (mm) per episode")
    for v in values:
        with torch.no_grad():
            if args.scale_term is not None:
                factor.fill_(float(v))
            else:
                prm.copy_(torch.as_tensor(v, dtype=prm.dtype).reshape(prm.shape))
        t0 = time.time()
        res = [float(residual_per_frame(sim, o, ctx.scene).mean()) for o in obs]
        per = " ".join(f"{o.name}:{1000 * r:.1f}" for o, r in zip(obs, res))
        print(f"{name}={json.dumps(v)}: mean {1000 * np.mean(res):.2f} | {per} ({time.time() - t0:.0f} s)", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
