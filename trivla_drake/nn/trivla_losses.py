"""TriVLA's training losses, one per system and stage, on batched torch tensors: `compute_loss` (System 1's flow
matching, eq. 5, plus the instruction grounding's sub-goal loss), `compute_grounding_loss` (the grounding alone: the
bind phase), `compute_video_loss` (System 3, eq. 1), `compute_vlm_loss` and `score_vlm_answers` (System 2 on visual
questions). A mixin of `TriVLA` (nn/trivla.py), whose systems, normaliser and encoders it uses."""

from __future__ import annotations

from typing import Any, Mapping

import torch

from trivla_drake.nn.embodiment import check_embodiment_ids
from trivla_drake.nn.instruction_grounding import grounding_loss


class TriVLATrainingLosses:
    """The training losses of `TriVLA` (mixed into it; not used alone)."""

    def _batch_tensor(
        self, batch: Mapping[str, Any], key: str, dtype: torch.dtype | None = torch.float32
    ) -> torch.Tensor:
        if key not in batch:
            raise ValueError(f"batch is missing {key!r}")
        t = torch.as_tensor(batch[key])
        return t.to(self.device, dtype) if dtype is not None else t.to(self.device)

    def compute_loss(
        self,
        batch: Mapping[str, Any],
        *,
        generator: torch.Generator | None = None,
        train_systems_2_3: bool = False,
        grounding_weight: float = 1.0,
    ) -> tuple[torch.Tensor, dict[str, float]]:
        """System 1's flow-matching loss (eq. 5 with velocity regression) on a batch of B samples.

        Keys: "action" float (B, H, A) and "state" float (B, state_dim), both unnormalised;
        "embodiment_id" long (B,) (default zeros); "action_is_pad" and "action_is_stale" bool (B, H)
        (optional: padding past an episode's end, and entries after a disturbed step of a DART
        demonstration; either leaves the entry out of the loss);
        and either raw inputs "static_rgb"/"wrist_rgb" uint8 (B, H, W, 3) + "instruction" list[str], or
        precomputed "q_vl" (B, S, D_llm) + optional "q_vl_mask" (B, S) and "dynamics_static"/
        "dynamics_wrist" (B, T+1, C, H_p, W_p). Systems 2 and 3 run without gradient unless train_systems_2_3.
        With `policy.instruction_grounding`, also "subgoal_position" float (B, 3) [m] (data/subgoals.py)
        and optionally "subgoal_in_loss" bool (B,) (only those rows count): the loss adds
        `grounding_weight` x the grounding's sub-goal loss.
        Returns (loss, info)."""
        pol = self.config.policy
        actions = self._batch_tensor(batch, "action")
        state = self._batch_tensor(batch, "state")
        b = actions.shape[0]
        if tuple(actions.shape[1:]) != (pol.action_horizon, pol.action_dim):
            raise ValueError(
                f"batch['action'] must be (B, {pol.action_horizon}, {pol.action_dim}); got {tuple(actions.shape)}"
            )
        if tuple(state.shape) != (b, pol.state_dim):
            raise ValueError(f"batch['state'] must be ({b}, {pol.state_dim}); got {tuple(state.shape)}")
        for key, value in (("action", actions), ("state", state)):
            if not torch.isfinite(value).all():
                raise ValueError(f"batch['{key}'] has NaN or infinite entries")
        eid = (
            self._batch_tensor(batch, "embodiment_id", torch.long)
            if "embodiment_id" in batch
            else torch.zeros(b, dtype=torch.long, device=self.device)
        )
        check_embodiment_ids(eid, pol.num_embodiments)
        excluded = [torch.as_tensor(batch[k], dtype=torch.bool, device=self.device)
                    for k in ("action_is_pad", "action_is_stale") if batch.get(k) is not None]
        action_mask = None if not excluded else ~torch.stack(excluded).any(0)

        with torch.set_grad_enabled(train_systems_2_3 and torch.is_grad_enabled()):
            q_vl = q_vl_mask = f_static = f_wrist = None
            if self.vision_language is not None:
                q_vl, q_vl_mask = self._batch_q_vl(batch)
            if self.dynamics is not None:
                if "dynamics_static" in batch:
                    f_static = self._batch_tensor(batch, "dynamics_static")
                    f_wrist = self._batch_tensor(batch, "dynamics_wrist")
                else:
                    f_static, f_wrist = self.encode_dynamics_batch(
                        batch["static_rgb"], batch["wrist_rgb"], list(batch["instruction"]), generator=generator
                    )
        q_s = self.policy.encode_state(self._state_input(state), eid)
        q_s, memory, mask, subgoal = self._conditions(q_s, q_vl, q_vl_mask, f_static, f_wrist, state)
        flow_loss, t = self.policy.loss(
            self.normalizer.normalize_action(actions),
            q_s,
            memory,
            mask,
            eid,
            action_mask=action_mask,
            generator=generator,
        )
        info = {"flow_time_mean": float(t.mean())}
        loss = flow_loss
        if subgoal is not None:
            aux = self._subgoal_loss(batch, subgoal)
            loss = flow_loss + grounding_weight * aux
            info.update(flow_loss=float(flow_loss.detach()), grounding_loss=float(aux.detach()))
        info["loss"] = float(loss.detach())
        return loss, info

    def compute_grounding_loss(self, batch: Mapping[str, Any]) -> tuple[torch.Tensor, dict[str, float]]:
        """The instruction grounding's sub-goal loss alone (no flow matching): "subgoal_position" float
        (B, 3) [m], optional "subgoal_in_loss" bool (B,) (only those rows count), and precomputed
        "q_vl" (B, S, D_llm) with optional "q_vl_mask" (B, S), or raw "static_rgb"/"wrist_rgb" +
        "instruction" (System 2 then runs without gradient). Returns (loss, info)."""
        if self.policy.grounding is None:
            raise ValueError("this System 1 has no instruction grounding (policy.instruction_grounding is off)")
        with torch.no_grad():
            q_vl, q_vl_mask = self._batch_q_vl(batch)
        if self.config.policy.grounding_reads_gripper and "state" not in batch:
            raise ValueError("batch is missing 'state': this grounding reads the gripper's closure "
                             "(policy.grounding_reads_gripper)")
        state = self._batch_tensor(batch, "state") if "state" in batch else None
        loss = self._subgoal_loss(batch, self.subgoal_of_features(q_vl, q_vl_mask, state))
        return loss, {"grounding_loss": float(loss.detach()), "loss": float(loss.detach())}

    def _batch_q_vl(self, batch: Mapping[str, Any]) -> tuple[torch.Tensor, torch.Tensor | None]:
        """A batch's Q_vl and its mask: precomputed "q_vl" (+ optional "q_vl_mask"), or System 2 run on
        "static_rgb"/"wrist_rgb" + "instruction"."""
        if "q_vl" in batch:
            mask = self._batch_tensor(batch, "q_vl_mask", torch.bool) if "q_vl_mask" in batch else None
            return self._batch_tensor(batch, "q_vl"), mask
        return self.encode_vision_language_batch(batch["static_rgb"], batch["wrist_rgb"], list(batch["instruction"]))

    def _subgoal_loss(self, batch: Mapping[str, Any], subgoal: torch.Tensor) -> torch.Tensor:
        """grounding_loss of predicted sub-goals (B, 3) against the batch's labels ("subgoal_position"), after
        checking them."""
        b = subgoal.shape[0]
        if "subgoal_position" not in batch:
            raise ValueError("batch is missing 'subgoal_position', the instruction grounding's labels "
                             "(a dataset with observation.tcp_pose)")
        target = self._batch_tensor(batch, "subgoal_position")
        if tuple(target.shape) != (b, 3) or not torch.isfinite(target).all():
            raise ValueError(f"batch['subgoal_position'] must be finite ({b}, 3); got {tuple(target.shape)}")
        counts = batch.get("subgoal_in_loss")
        if counts is not None:
            counts = torch.as_tensor(counts, dtype=torch.bool, device=self.device)
            if tuple(counts.shape) != (b,):
                raise ValueError(f"batch['subgoal_in_loss'] must be ({b},); got {tuple(counts.shape)}")
        return grounding_loss(subgoal, target, counts)

    def compute_video_loss(
        self, batch: Mapping[str, Any], *, generator: torch.Generator | None = None
    ) -> tuple[torch.Tensor, dict[str, float]]:
        """System 3's eq. (1) on clips: "video" uint8 (B, T+1, H, W, 3) (frame 0 = current frame, any camera)
        and "instruction" list[str]. Returns (loss, info)."""
        if self.dynamics is None:
            raise ValueError("System 3 is disabled in this model (config.use_system3 = False)")
        video = self._batch_tensor(batch, "video", None)
        if video.dtype != torch.uint8 or video.dim() != 5 or video.shape[-1] != 3:
            raise ValueError(f"batch['video'] must be uint8 (B, T+1, H, W, 3); got {video.dtype} {tuple(video.shape)}")
        if "instruction" not in batch:
            raise ValueError("batch is missing 'instruction'")
        ids = self._dyn_instruction_ids(list(batch["instruction"]), "batch['instruction']")
        return self.dynamics.video_loss(video, ids, generator=generator)

    def score_vlm_answers(
        self, static_rgb: Any, wrist_rgb: Any, questions: list[str], candidates: list[list[str]]
    ) -> list[torch.Tensor]:
        """log p(answer | images, question) under System 2's LM head, summed over the answer's tokens,
        for every candidate answer of every sample (images uint8 (B, H, W, 3) per view; each sample's
        images are encoded once). Returns B tensors of shape (K_b,). Used to score visual questions."""
        import torch.nn.functional as F

        vl = self.vision_language
        if vl is None:
            raise ValueError("score_vlm_answers needs System 2 (config.use_system2 = True)")
        images = torch.stack([self._images(static_rgb, "static_rgb"), self._images(wrist_rgb, "wrist_rgb")], dim=1)
        ids, states = self._vl_inputs(list(questions), "question")
        batch, views = images.shape[:2]
        tokens = vl.encode_images(images.flatten(0, 1)).unflatten(0, (batch, views))
        owner = [b for b, cands in enumerate(candidates) for _ in cands]
        flat_answers = [a for cands in candidates for a in cands]
        prompts = vl.build_prompts([ids[b] for b in owner], views, flat_answers)
        owned_states = None if states is None else (states[0][owner], states[1][owner])
        embeds, mask, labels = vl.assemble(tokens[owner], prompts, with_answers=True, instruction_states=owned_states)
        logits = vl.llm(inputs_embeds=embeds, attention_mask=mask.long()).logits.float()
        target = labels[:, 1:]
        logp = F.log_softmax(logits[:, :-1], dim=-1)
        picked = logp.gather(-1, target.clamp_min(0).unsqueeze(-1)).squeeze(-1)
        scores = (picked * (target >= 0)).sum(-1)
        return list(torch.split(scores, [len(c) for c in candidates]))

    def compute_vlm_loss(
        self, batch: Mapping[str, Any], *, dense_weight: float = 0.0,
    ) -> tuple[torch.Tensor, dict[str, float]]:
        """System 2's next-token loss on answers to visual questions (the mean over the batch's answer tokens):
        "static_rgb"/"wrist_rgb" uint8 (B, H, W, 3), "instruction" list[str] (the question) and "answer"
        list[str]. With `dense_weight` > 0, plus that times the dense loss of System 2's block head on the same
        image tokens, against "block_labels" uint8 (B, 2, H, W) (static, wrist; 0 nothing, 1 + k
        block k). Returns (loss, info)."""
        if self.vision_language is None:
            raise ValueError("System 2 is disabled in this model (config.use_system2 = False)")
        if not dense_weight >= 0:
            raise ValueError(f"dense_weight must be >= 0; got {dense_weight}")
        for key in ("static_rgb", "wrist_rgb", "instruction", "answer") + (("block_labels",) if dense_weight else ()):
            if key not in batch:
                raise ValueError(f"batch is missing {key!r}")
        images = torch.stack(
            [
                self._images(batch["static_rgb"], "batch['static_rgb']"),
                self._images(batch["wrist_rgb"], "batch['wrist_rgb']"),
            ],
            dim=1,
        )
        ids, states = self._vl_inputs(list(batch["instruction"]), "batch['instruction']")
        answers = list(batch["answer"])
        if len(answers) != len(ids) or not all(isinstance(a, str) and a for a in answers):
            raise ValueError("batch['answer'] must be one non-empty str per sample")
        labels = None
        if dense_weight:
            labels = torch.as_tensor(batch["block_labels"])
            if labels.dtype != torch.uint8 or tuple(labels.shape) != (images.shape[0], 2) + tuple(images.shape[2:4]):
                raise ValueError(f"batch['block_labels'] must be uint8 {(images.shape[0], 2) + tuple(images.shape[2:4])}; "
                                 f"got {labels.dtype} {tuple(labels.shape)}")
        loss, dense = self.vision_language.vlm_losses(images, ids, answers, block_labels=labels,
                                                      instruction_states=states)
        info = {"vlm_loss": float(loss.detach())}
        if dense is not None:
            info["dense_loss"] = float(dense.detach())
            loss = loss + dense_weight * dense
        return loss, info
