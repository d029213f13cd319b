"""The download-free byte-level tokenizer and the chat prompt."""

import pytest

from trivla_drake.nn.chat_prompt import build_chat_prompt, tokenize_instruction
from trivla_drake.nn.tokenizer import ByteTokenizer, load_tokenizer


def test_byte_tokenizer_is_deterministic_and_round_trips():
    tok = ByteTokenizer()
    text = "pick up the red block — then place it <|im_end|>"
    ids = tok.encode(text)
    assert ids == ByteTokenizer().encode(text)
    assert tok.decode(ids) == text
    assert tok.token_id("<|im_end|>") in ids
    assert max(ids) < tok.vocab_size == ByteTokenizer.VOCAB_SIZE
    plain = tok.encode(text, allow_special=False)
    assert all(i < 256 for i in plain) and tok.decode(plain) == text


def test_load_tokenizer_without_path_is_byte_level_and_bad_path_is_an_error(tmp_path):
    assert isinstance(load_tokenizer(None), ByteTokenizer)
    with pytest.raises(ValueError, match="not a directory"):
        load_tokenizer(str(tmp_path / "missing"))


def test_chat_prompt_places_images_then_instruction():
    tok = ByteTokenizer()
    ids = tokenize_instruction(tok, "open the drawer", 64, "instruction")
    prompt = build_chat_prompt(tok, ids, num_images=2, answer="yes")
    assert prompt.num_images == 2
    assert tok.decode(list(prompt.text_pieces[0])) == "<|im_start|>user\n<img>"
    assert tok.decode(list(prompt.text_pieces[1])) == "</img><img>"
    assert tok.decode(list(prompt.text_pieces[2])) == (
        "</img>\nopen the drawer<|im_end|>\n<|im_start|>assistant\n"
    )
    assert tok.decode(list(prompt.answer_ids)) == "yes<|im_end|>"


@pytest.mark.parametrize("bad, match", [("", "empty"), ("   ", "empty"), ("x" * 65, "too long"), (3, "str")])
def test_bad_instructions_are_named(bad, match):
    with pytest.raises(ValueError, match=f"instruction.*{match}|{match}.*instruction|instruction must be a {match}"):
        tokenize_instruction(ByteTokenizer(), bad, 64, "instruction")
