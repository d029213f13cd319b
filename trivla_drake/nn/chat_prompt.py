"""The chat-style prompt System 2 feeds the LLM: images and the instruction in one user turn.

    <|im_start|>user\n<img>[64 static-view tokens]</img><img>[64 wrist-view tokens]</img>\n
    {instruction}<|im_end|>\n<|im_start|>assistant\n[{answer}<|im_end|>]

ChatML markup as SmolLM2 uses, <img>...</img> image slots as Eagle-2 uses. Image embeddings are
spliced between the text pieces directly, so no image-placeholder token is needed in the vocabulary.
"""

from __future__ import annotations

from dataclasses import dataclass

from trivla_drake.nn.tokenizer import TextTokenizer

PROMPT_HEAD = "<|im_start|>user\n<img>"
PROMPT_BETWEEN_IMAGES = "</img><img>"
PROMPT_AFTER_IMAGES = "</img>\n"
PROMPT_TAIL = "<|im_end|>\n<|im_start|>assistant\n"
ANSWER_END = "<|im_end|>"


@dataclass(frozen=True)
class ChatPrompt:
    """Token ids of one prompt: `text_pieces[i]` precedes image i; the last piece follows the last image."""

    text_pieces: tuple[tuple[int, ...], ...]
    answer_ids: tuple[int, ...] = ()  # target tokens (answer + end of turn) for the LM loss; may be empty

    @property
    def num_images(self) -> int:
        """Number of image slots."""
        return len(self.text_pieces) - 1


def build_chat_prompt(
    tokenizer: TextTokenizer, instruction_ids: list[int], num_images: int, answer: str | None = None
) -> ChatPrompt:
    """Assembles the prompt around already-tokenised instruction ids (see `tokenize_instruction`)."""
    pieces = [tuple(tokenizer.encode(PROMPT_HEAD))]
    pieces += [tuple(tokenizer.encode(PROMPT_BETWEEN_IMAGES)) for _ in range(num_images - 1)]
    tail = tokenizer.encode(PROMPT_AFTER_IMAGES) + list(instruction_ids) + tokenizer.encode(PROMPT_TAIL)
    pieces.append(tuple(tail))
    answer_ids: tuple[int, ...] = ()
    if answer is not None:
        answer_ids = tuple(tokenizer.encode(answer, allow_special=False) + tokenizer.encode(ANSWER_END))
    return ChatPrompt(text_pieces=tuple(pieces), answer_ids=answer_ids)


def check_instruction_text(instruction: object, field: str) -> str:
    """A user instruction without its surrounding white space; ValueError naming `field` if it is not a
    non-empty string."""
    if not isinstance(instruction, str):
        raise ValueError(f"{field} must be a str; got {type(instruction).__name__}")
    if not instruction.strip():
        raise ValueError(f"{field} is empty; give the task in words, e.g. 'pick up the red block'")
    return instruction.strip()


def tokenize_instruction(tokenizer: TextTokenizer, instruction: object, max_tokens: int, field: str) -> list[int]:
    """Token ids of a user instruction; raises ValueError naming `field` if it is not a non-empty
    string of at most `max_tokens` tokens. Markup inside the instruction is treated as plain text."""
    ids = tokenizer.encode(check_instruction_text(instruction, field), allow_special=False)
    if len(ids) > max_tokens:
        raise ValueError(f"{field} is too long: {len(ids)} tokens, at most {max_tokens} are accepted")
    return ids
