"""System 2, the vision-language module: Eagle-2's design on transformers' SigLIP and Llama classes.

Each 224x224 view -> SigLIP (16x16 patch tokens) -> pixel shuffle 0.5 (8x8 tokens, 4x channels) ->
LayerNorm-Linear-GELU-Linear projector = 64 tokens per frame at LLM width. The views are spliced into a
chat prompt with the tokenised instruction and run through the Llama LLM; Q_vl are the hidden states
output by decoder layer `select_layer` (the paper's 12th), and the layers above it never run.

With a pretrained text encoder entering System 2 (`TriVLAConfig.text_encoder`), the instruction's token
embeddings are its token states projected to the LLM's width (`instruction_projection`), at the same place of
the same prompt: the prompt's markup is still embedded by the LLM.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

from trivla_drake.nn import pretrained
from trivla_drake.nn.chat_prompt import PROMPT_AFTER_IMAGES, PROMPT_TAIL, ChatPrompt, build_chat_prompt
from trivla_drake.nn.config import VisionLanguageConfig
from trivla_drake.nn.early_exit import run_until
from trivla_drake.nn.pixel_shuffle import pixel_shuffle
from trivla_drake.nn.tokenizer import TextTokenizer

IGNORE_INDEX = -100  # label of positions the LM loss skips (prompt and image tokens)


DENSE_MIN_FRACTION = 0.005
"""A token's image cell (or sub-cell) shows a block when at least this share of its pixels do: 4 of
28 x 28, or any pixel of a 7 x 7 sub-cell (`VisionLanguageConfig.dense_subcells` 4)."""


def dense_block_targets(labels: torch.Tensor, grid: int, classes: int, subcells: int = 1) -> torch.Tensor:
    """uint8 label maps (N, S, S), 0 for nothing and 1 + k for block k, -> float (N, grid^2, subcells^2
    * classes): 1 where at least DENSE_MIN_FRACTION of the pixels of a sub-cell of the token's cell show
    block k (for small sub-cells, any pixel). The token's cell is split into `subcells` x `subcells`
    sub-cells (1: the whole cell), in
    row-major order, each with its `classes` entries. Cells are in row-major order, the order of the
    image tokens after pixel shuffle."""
    n, size, width = labels.shape
    if size != width or size % (grid * subcells):
        raise ValueError(f"block labels must be square with a side divisible by {grid} tokens x {subcells} "
                         f"sub-cells; got {size} x {width}")
    if int(labels.max()) > classes:
        raise ValueError(f"block labels go up to {int(labels.max())}, the head has {classes} classes")
    onehot = F.one_hot(labels.long(), classes + 1)[..., 1:].float()
    fine = grid * subcells
    pixels = size // fine
    share = onehot.reshape(n, fine, pixels, fine, pixels, classes).mean(dim=(2, 4))  # (N, fine, fine, K)
    share = share.reshape(n, grid, subcells, grid, subcells, classes).permute(0, 1, 3, 2, 4, 5)
    return (share.reshape(n, grid * grid, subcells * subcells * classes) >= DENSE_MIN_FRACTION).float()


def images_to_siglip_input(images: torch.Tensor, dtype: torch.dtype) -> torch.Tensor:
    """uint8 (N, H, W, 3) RGB -> float (N, 3, H, W) scaled to [-1, 1] (SigLIP's mean = std = 0.5)."""
    x = images.permute(0, 3, 1, 2).to(dtype) / 255.0
    return (x - 0.5) / 0.5


class VisionLanguageModule(nn.Module):
    """System 2: SigLIP + pixel shuffle + MLP projector + Llama LLM read out at a middle layer (Q_vl)."""

    def __init__(
        self,
        config: VisionLanguageConfig,
        tokenizer: TextTokenizer,
        vision_encoder: nn.Module,
        projector: nn.Sequential,
        llm: nn.Module,
        pixel_shuffle_ratio: float,
        instruction_width: int | None = None,
    ) -> None:
        """`instruction_width`: the width of a pretrained text encoder's token states that stand for the
        instruction's tokens (projected to the LLM's width); None: the LLM embeds the instruction's tokens."""
        super().__init__()
        self.config = config
        self.tokenizer = tokenizer
        self.vision_encoder = vision_encoder
        self.projector = projector
        self.llm = llm
        self.pixel_shuffle_ratio = pixel_shuffle_ratio
        vcfg = vision_encoder.config
        self.image_size = vcfg.image_size
        grid = vcfg.image_size // vcfg.patch_size
        self.num_image_tokens = grid * grid // round(1 / pixel_shuffle_ratio) ** 2
        self.block_head = (nn.Linear(llm.config.hidden_size, config.dense_classes * config.dense_subcells**2)
                           if config.dense_classes > 0 else None)
        self.instruction_projection = (nn.Linear(instruction_width, llm.config.hidden_size)
                                       if instruction_width is not None else None)
        num_layers = len(llm.model.layers)
        if not 1 <= config.select_layer <= num_layers:
            raise ValueError(
                f"vision_language.select_layer ({config.select_layer}) exceeds the LLM's {num_layers} layers"
            )
        if tokenizer.vocab_size > llm.config.vocab_size:
            raise ValueError(
                f"the tokenizer has {tokenizer.vocab_size} ids but the LLM vocabulary only "
                f"{llm.config.vocab_size} (vision_language.llm.vocab_size)"
            )

    @classmethod
    def from_config(
        cls,
        config: VisionLanguageConfig,
        tokenizer: TextTokenizer,
        *,
        component_configs: dict | None = None,
        load_pretrained: bool = True,
        instruction_width: int | None = None,
    ) -> "VisionLanguageModule":
        """Builds the module: from recorded component configs (a checkpoint), from local pretrained
        directories named in `config` (when load_pretrained), or randomly initialised from its shapes.
        `instruction_width`: see `__init__`."""
        ratio = config.pixel_shuffle_ratio
        layers = config.select_layer if config.drop_unused_llm_layers else None
        if component_configs is not None:
            vision = pretrained.build_siglip_vision(component_configs["vision"])
            llm = pretrained.build_llama(component_configs["llm"])
            ratio = component_configs.get("pixel_shuffle_ratio", ratio)
            projector = pretrained.eagle_projector(vision.config.hidden_size, llm.config.hidden_size, ratio)
        elif load_pretrained and config.eagle2_path:
            parts = pretrained.load_eagle2(config.eagle2_path, num_hidden_layers=layers)
            vision, projector, llm, ratio = parts.vision_encoder, parts.projector, parts.llm, parts.pixel_shuffle_ratio
        else:
            if load_pretrained and config.siglip_path:
                vision = pretrained.load_siglip_vision(config.siglip_path)
            else:
                vision = pretrained.build_siglip_vision(pretrained.siglip_vision_config(config.vision))
            if load_pretrained and config.llm_path:
                llm = pretrained.load_llama(config.llm_path, num_hidden_layers=layers)
            else:
                llm = pretrained.build_llama(
                    pretrained.llama_config(config.llm, num_hidden_layers=layers, pad_token_id=tokenizer.pad_token_id)
                )
            projector = pretrained.eagle_projector(vision.config.hidden_size, llm.config.hidden_size, ratio)
        return cls(config, tokenizer, vision, projector, llm, ratio, instruction_width)

    def component_configs(self) -> dict:
        """Library configs of the parts, enough to rebuild this architecture without the original files."""
        return {
            "vision": pretrained.component_config_dict(self.vision_encoder),
            "llm": pretrained.component_config_dict(self.llm),
            "pixel_shuffle_ratio": self.pixel_shuffle_ratio,
        }

    @property
    def hidden_size(self) -> int:
        """Width of Q_vl (the LLM's hidden size)."""
        return self.llm.config.hidden_size

    def instruction_offset(self, num_views: int) -> int:
        """Position of the instruction's first token in Q_vl: the prompt head, the image tokens and the
        markup between them come first and are laid out the same in every prompt."""
        pieces = build_chat_prompt(self.tokenizer, [], num_views).text_pieces
        head = sum(len(p) for p in pieces[:-1]) + num_views * self.num_image_tokens
        return head + len(self.tokenizer.encode(PROMPT_AFTER_IMAGES))

    def image_token_span(self, view: int) -> tuple[int, int]:
        """(first index, count) of image `view`'s tokens in Q_vl (0: static, 1: wrist, as the prompt
        lays them out)."""
        pieces = build_chat_prompt(self.tokenizer, [], view + 1).text_pieces
        return sum(len(p) for p in pieces[:-1]) + view * self.num_image_tokens, self.num_image_tokens

    def drop_layers_above_readout(self) -> None:
        """Removes the LLM decoder layers above `select_layer`, which computing Q_vl never runs (GR00T
        builds its LLM this way), and records it in the config, so a saved checkpoint rebuilds the
        shorter LLM. Q_vl is unchanged; the LLM's answers (VQA) are not, so a model trimmed this way is
        for inference, not for the vlm stage."""
        keep = self.config.select_layer
        if len(self.llm.model.layers) > keep:
            self.llm.model.layers = nn.ModuleList(list(self.llm.model.layers)[:keep])
            llm_config = self.llm.config
            llm_config.num_hidden_layers = keep
            if getattr(llm_config, "layer_types", None) is not None:  # e.g. Qwen2 LLMs list one per layer
                llm_config.layer_types = list(llm_config.layer_types)[:keep]
        self.config.drop_unused_llm_layers = True

    @property
    def readout_layer(self) -> nn.Module:
        """The LLM decoder layer whose output is Q_vl."""
        return self.llm.model.layers[self.config.select_layer - 1]

    def encode_images(self, images: torch.Tensor) -> torch.Tensor:
        """uint8 (N, H, W, 3) frames -> (N, num_image_tokens, hidden) projected image tokens."""
        dtype = self.projector[1].weight.dtype
        pixels = images_to_siglip_input(images.to(self.projector[1].weight.device), dtype)
        patches = self.vision_encoder(pixel_values=pixels).last_hidden_state  # (N, G*G, Cv)
        return self.projector(pixel_shuffle(patches, self.pixel_shuffle_ratio))

    def instruction_placeholders(self, mask: torch.Tensor) -> list[list[int]]:
        """Instruction ids standing for a text encoder's token states (mask (B, L)): as many pad ids as each
        instruction has states, replaced by the projected states in `assemble`."""
        return [[self.tokenizer.pad_token_id] * int(n) for n in mask.sum(dim=1).tolist()]

    def build_prompts(
        self, instruction_ids: list[list[int]], num_images: int, answers: list[str] | None = None
    ) -> list[ChatPrompt]:
        """Chat prompts for already-tokenised instructions (and answers, for the LM loss)."""
        return [
            build_chat_prompt(self.tokenizer, ids, num_images, None if answers is None else answers[i])
            for i, ids in enumerate(instruction_ids)
        ]

    def assemble(
        self, image_tokens: torch.Tensor, prompts: list[ChatPrompt], *, with_answers: bool = False,
        instruction_states: tuple[torch.Tensor, torch.Tensor] | None = None,
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Splices image tokens (B, V, n, D) into the embedded prompts; right-pads the batch.
        With `instruction_states` (a text encoder's token states (B, L, W) and mask (B, L); the prompts then hold
        `instruction_placeholders`), the instruction's positions get the projected states instead.
        Returns input embeddings (B, S, D), attention mask (B, S) and LM labels (B, S)."""
        self._check_instruction_states(instruction_states)
        batch, views, n, _ = image_tokens.shape
        lengths = [
            sum(len(p) for p in prompt.text_pieces) + views * n + (len(prompt.answer_ids) if with_answers else 0)
            for prompt in prompts
        ]
        seq = max(lengths)
        device = image_tokens.device
        ids = torch.full((batch, seq), self.tokenizer.pad_token_id, dtype=torch.long)
        labels = torch.full((batch, seq), IGNORE_INDEX, dtype=torch.long)
        mask = torch.zeros(batch, seq, dtype=torch.bool)
        is_image = torch.zeros(batch, seq, dtype=torch.bool)
        is_instruction = torch.zeros(batch, seq, dtype=torch.bool)
        after_images = len(self.tokenizer.encode(PROMPT_AFTER_IMAGES))
        tail = len(self.tokenizer.encode(PROMPT_TAIL))
        instruction_lengths = None if instruction_states is None else instruction_states[1].sum(dim=1).tolist()
        for b, prompt in enumerate(prompts):
            if prompt.num_images != views:
                raise ValueError(f"prompt {b} has {prompt.num_images} image slots for {views} views")
            pos = 0
            for i, piece in enumerate(prompt.text_pieces):
                if i == views and instruction_lengths is not None:  # the last piece: markup, instruction, turn end
                    if len(piece) != after_images + int(instruction_lengths[b]) + tail:
                        raise ValueError(f"prompt {b} holds {len(piece) - after_images - tail} instruction ids for "
                                         f"{int(instruction_lengths[b])} text encoder states: build it from "
                                         "instruction_placeholders")
                    is_instruction[b, pos + after_images : pos + after_images + int(instruction_lengths[b])] = True
                ids[b, pos : pos + len(piece)] = torch.tensor(piece, dtype=torch.long)
                pos += len(piece)
                if i < views:
                    is_image[b, pos : pos + n] = True
                    pos += n
            if with_answers and prompt.answer_ids:
                answer = torch.tensor(prompt.answer_ids, dtype=torch.long)
                ids[b, pos : pos + len(answer)] = answer
                labels[b, pos : pos + len(answer)] = answer
                pos += len(answer)
            mask[b, :pos] = True
        ids, labels, mask, is_image = (t.to(device) for t in (ids, labels, mask, is_image))
        embeds = self.llm.get_input_embeddings()(ids)
        # Under autocast the image tokens come out in the autocast dtype while the embedding table stays float32.
        image_tokens = image_tokens.reshape(-1, image_tokens.shape[-1]).to(embeds.dtype)
        embeds = embeds.masked_scatter(is_image.unsqueeze(-1), image_tokens)
        if instruction_states is not None:
            states, states_mask = instruction_states
            projection = self.instruction_projection
            projected = projection(states.to(device, projection.weight.dtype))[states_mask.to(device)]
            embeds = embeds.masked_scatter(is_instruction.to(device).unsqueeze(-1), projected.to(embeds.dtype))
        return embeds, mask, labels

    def _check_instruction_states(self, instruction_states: tuple[torch.Tensor, torch.Tensor] | None) -> None:
        """ValueError unless this System 2 gets a text encoder's states exactly when it reads them."""
        if self.instruction_projection is not None and instruction_states is None:
            raise ValueError("this System 2 reads the instruction as a pretrained text encoder's token states "
                             "(TriVLAConfig.text_encoder): pass instruction_states")
        if self.instruction_projection is None and instruction_states is not None:
            raise ValueError("this System 2 embeds the instruction's tokens itself (no TriVLAConfig.text_encoder): "
                             "instruction_states are not read")

    def forward(
        self, images: torch.Tensor, instruction_ids: list[list[int]],
        instruction_states: tuple[torch.Tensor, torch.Tensor] | None = None,
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """images: uint8 (B, V, H, W, 3); instruction_ids: B token lists (`instruction_placeholders` with
        `instruction_states`, see `assemble`).
        Returns Q_vl (B, S, hidden), the output of LLM layer `select_layer`, and its mask (B, S)."""
        batch, views = images.shape[:2]
        tokens = self.encode_images(images.flatten(0, 1)).unflatten(0, (batch, views))
        embeds, mask, _ = self.assemble(tokens, self.build_prompts(instruction_ids, views),
                                        instruction_states=instruction_states)
        layer = self.readout_layer
        (q_vl,) = run_until(
            lambda: self.llm.model(inputs_embeds=embeds, attention_mask=mask.long()), [layer], layer
        )
        return q_vl, mask

    def dense_block_loss(self, tokens: torch.Tensor, block_labels: torch.Tensor) -> torch.Tensor:
        """Binary cross-entropy of `block_head` on projected image tokens (N, n, D) against the cells'
        blocks in uint8 label maps (N, S, S) (`dense_block_targets`)."""
        if self.block_head is None:
            raise ValueError("this System 2 has no block head (vision_language.dense_classes is 0)")
        grid = round(self.num_image_tokens**0.5)
        targets = dense_block_targets(block_labels.to(tokens.device), grid, self.config.dense_classes,
                                      self.config.dense_subcells)
        return F.binary_cross_entropy_with_logits(self.block_head(tokens).float(), targets)

    def vlm_losses(
        self, images: torch.Tensor, instruction_ids: list[list[int]], answers: list[str], *,
        block_labels: torch.Tensor | None = None,
        instruction_states: tuple[torch.Tensor, torch.Tensor] | None = None,
    ) -> tuple[torch.Tensor, torch.Tensor | None]:
        """Next-token cross-entropy on the answer tokens of a visual question (System 2 pretraining): the mean
        over every answer token of the batch. With `block_labels` (B, V, S, S) also the dense loss of the same
        image tokens (`dense_block_loss`), else None. `instruction_states`: see `assemble`. Returns (LM loss,
        dense loss)."""
        batch, views = images.shape[:2]
        flat = self.encode_images(images.flatten(0, 1))
        dense = None if block_labels is None else self.dense_block_loss(flat, block_labels.flatten(0, 1))
        tokens = flat.unflatten(0, (batch, views))
        prompts = self.build_prompts(instruction_ids, views, answers)
        embeds, mask, labels = self.assemble(tokens, prompts, with_answers=True, instruction_states=instruction_states)
        return self.llm(inputs_embeds=embeds, attention_mask=mask.long(), labels=labels).loss, dense
