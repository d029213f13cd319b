"""Does System 2's Q_vl tell a scene with a stack from one without? (results/stacked_hold, reproduce step 59)

    python results/stacked_hold/stack_probe.py CHECKPOINT OUT.json [--scenes 12000] [--test-scenes 600]
        [--stacked-picks 0.3] [--steps 300] [--threads 1]

The grounding's read-out, re-fitted with stacked picks, trades the table scenes' sub-goals against the stacked
ones' (`--hold`): as if it could not tell them apart. This probes the image tokens it reads: a logistic regression
(L2, Adam), per view and both, on the lift, place in bowl and stack scenes of the re-fit's training set (12000
scenes, `--stacked-picks 0.3`: those with a stack pick its top block, the others have no stack), tested on the
unseen test sets' same tasks (the 300 stacked picks of `test_stacked_picks` against the plain ones of
`test_scenes`). Q_vl comes from refit_grounding.py's cache (computed if missing). Prints and writes the held-out
accuracy and the balanced accuracy of each probe, with what always guessing the larger class scores."""
import argparse
import importlib.util
import json
from pathlib import Path

import numpy as np
import torch

from trivla_drake.nn import load_checkpoint
from trivla_drake.tasks.suite import STACKED_PICK_TASKS

HERE = Path(__file__).resolve().parent


def refit_script():
    spec = importlib.util.spec_from_file_location("refit_grounding", HERE.parent / "grounding_scenes" / "refit_grounding.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def view_features(samples, rows: np.ndarray, span: tuple[int, int]) -> torch.Tensor:
    """One view's image tokens of `rows`, flattened (R, 64 * D), float32."""
    start, count = span
    return samples.q_vl[torch.from_numpy(rows), start:start + count].float().flatten(1)


def fit_probe(x: torch.Tensor, y: torch.Tensor, *, steps: int, weight_decay: float = 1e-2,
              seed: int = 0) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Logistic regression on standardised features: (weights, bias, feature mean, feature std)."""
    torch.manual_seed(seed)
    mean, std = x.mean(0), x.std(0).clamp(min=1e-4)
    z = (x - mean) / std
    w = torch.zeros(x.shape[1], requires_grad=True)
    b = torch.zeros((), requires_grad=True)
    optimizer = torch.optim.Adam([w, b], lr=1e-3)
    for _ in range(steps):
        loss = torch.nn.functional.binary_cross_entropy_with_logits(z @ w + b, y) + weight_decay * w.square().sum()
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
    return w.detach(), b.detach(), mean, std


def scores(predicted: np.ndarray, truth: np.ndarray) -> dict[str, float]:
    """Accuracy and balanced accuracy (the mean of each class's recall) of bool predictions."""
    recalls = [float((predicted[truth == c] == c).mean()) for c in (True, False)]
    return {"accuracy": round(float((predicted == truth).mean()), 3), "balanced_accuracy": round(sum(recalls) / 2, 3),
            "stacked_recall": round(recalls[0], 3), "plain_recall": round(recalls[1], 3)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("checkpoint")
    parser.add_argument("out")
    parser.add_argument("--scenes", type=int, default=12000, help="the training set's scenes (the re-fit's)")
    parser.add_argument("--test-scenes", type=int, default=600)
    parser.add_argument("--stacked-picks", type=float, default=0.3, help="the training set's stacked picks (the re-fit's)")
    parser.add_argument("--steps", type=int, default=300)
    parser.add_argument("--threads", type=int, default=1)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    refit = refit_script()
    model = load_checkpoint(args.checkpoint).eval()
    digest = refit.files_digest(Path(args.checkpoint), "*")
    train = refit.rendered(model, args.scenes, refit.TRAIN_SEED, stacked_picks=args.stacked_picks, checkpoint_digest=digest)
    tests = [refit.rendered(model, args.test_scenes, refit.TEST_SEED, stacked_picks=1.0, checkpoint_digest=digest),
             refit.rendered(model, args.test_scenes, refit.TEST_SEED, checkpoint_digest=digest)]
    spans = dict(zip(("static", "wrist"), model.policy.vl_view_spans))

    def rows_of(samples, stacked: bool | None) -> np.ndarray:
        picks = np.isin(samples.tasks, STACKED_PICK_TASKS)
        flags = samples.stacked_rows().numpy()
        return np.flatnonzero(picks if stacked is None else picks & (flags == stacked))

    train_rows = rows_of(train, None)
    y_train = train.stacked_rows()[torch.from_numpy(train_rows)].float()
    truth = np.concatenate([np.ones(len(rows_of(tests[0], True)), bool), np.zeros(len(rows_of(tests[1], False)), bool)])
    for what, labels in (("training", y_train.numpy().astype(bool)), ("test", truth)):
        if labels.all() or not labels.any():
            raise SystemExit(f"the {what} scenes of {', '.join(STACKED_PICK_TASKS)} are all of one kind "
                             f"({int(labels.sum())} of {len(labels)} stacked): a probe needs both; render more")
    report = {"checkpoint": args.checkpoint, "train": {"stacked": int(y_train.sum()), "plain": int(len(y_train) - y_train.sum())},
              "test": {"stacked": int(truth.sum()), "plain": int((~truth).sum())},
              "majority_class": round(float(max(truth.mean(), 1 - truth.mean())), 3), "probes": {}}
    for name, views in (("static", ["static"]), ("wrist", ["wrist"]), ("both", ["static", "wrist"])):
        x = torch.cat([view_features(train, train_rows, spans[v]) for v in views], 1)
        w, b, mean, std = fit_probe(x, y_train, steps=args.steps)
        x_test = torch.cat([torch.cat([view_features(t, rows_of(t, s), spans[v]) for v in views], 1)
                            for t, s in ((tests[0], True), (tests[1], False))])
        predicted = (((x_test - mean) / std) @ w + b > 0).numpy()
        train_predicted = (((x - mean) / std) @ w + b > 0).numpy()
        report["probes"][name] = {"held_out": scores(predicted, truth),
                                  "training": scores(train_predicted, y_train.numpy().astype(bool))}
        print(name, json.dumps(report["probes"][name]), flush=True)
    Path(args.out).write_text(json.dumps(report, indent=1))


if __name__ == "__main__":
    main()
