"""A fresh small vision-language model, built from a configuration: for machines that
have no weights to start from (`cavenav finetune --new small`).

It has SmolVLM's architecture (Idefics3: a vision transformer whose patches are merged
2x2 by pixel shuffle, then fed as tokens to a Llama-style language model) at a size that
trains on two CPU cores and answers in tens of milliseconds on a vehicle's computer. Its
tokenizer is a byte-level BPE trained on the texts it will read and write (the dataset's
prompts and replies), plus Idefics3's special tokens: words the pilot uses often
("forward", "standoff", "0.2 m") become single tokens, so a reply is short.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

__all__ = ["CHAT_TEMPLATE", "SMALL", "SmallVLM", "build_small_vlm"]

SPECIAL = ["<pad>", "<end_of_utterance>", "<fake_token_around_image>", "<image>", "<global-img>"]
# SmolVLM's chat form: "Role:" then the parts, each turn closed by <end_of_utterance>.
CHAT_TEMPLATE = (
    "{% for message in messages %}{{ message['role'] | capitalize }}:"
    "{% for part in message['content'] %}{% if part['type'] == 'text' %}{{ part['text'] }}"
    "{% else %}<image>{% endif %}{% endfor %}<end_of_utterance>\n{% endfor %}"
    "{% if add_generation_prompt %}Assistant:{% endif %}"
)


@dataclass(frozen=True)
class SmallVLM:
    """The size of a fresh model.

    Attributes:
        hidden: width of both towers.
        layers: transformer layers of each tower.
        heads: attention heads.
        image_px: the images' longest edge, pixels; they are cut into 16 px patches and
            merged 2x2, so an image is ``(image_px / 32) ** 2`` tokens (96 px: 9).
        vocab: BPE vocabulary, special tokens included.
    """

    hidden: int = 128
    layers: int = 4
    heads: int = 4
    image_px: int = 96
    vocab: int = 2048

    @property
    def image_tokens(self) -> int:
        return (self.image_px // 32) ** 2


SMALL = SmallVLM()  # about 2.5 M parameters (../shared/NOTES.md: 66 samples/s on 2 cores)


def build_small_vlm(
    folder: Path, texts: Iterable[str], size: SmallVLM = SMALL, seed: int = 0
) -> Path:
    """Write a randomly initialised Idefics3 of ``size`` and its processor to ``folder``,
    its tokenizer trained on ``texts``; the folder loads with ``AutoProcessor`` and
    ``AutoModelForImageTextToText``."""
    import torch
    from transformers import (
        Idefics3Config,
        Idefics3ForConditionalGeneration,
        Idefics3ImageProcessor,
        Idefics3Processor,
    )

    tokenizer = _tokenizer(texts, size.vocab)
    image_processor = Idefics3ImageProcessor(
        size={"longest_edge": size.image_px},
        max_image_size={"longest_edge": size.image_px},
        do_image_splitting=False,
    )
    processor = Idefics3Processor(
        image_processor=image_processor,
        tokenizer=tokenizer,
        chat_template=CHAT_TEMPLATE,
        image_seq_len=size.image_tokens,
    )
    tower = {
        "hidden_size": size.hidden,
        "intermediate_size": 2 * size.hidden,
        "num_hidden_layers": size.layers,
        "num_attention_heads": size.heads,
    }
    config = Idefics3Config(  # type: ignore[call-arg]  # pad_token_id: read by PretrainedConfig
        vision_config={**tower, "image_size": size.image_px, "patch_size": 16},
        text_config={
            **tower,
            "model_type": "llama",
            "num_key_value_heads": size.heads,
            "vocab_size": len(tokenizer),
            "max_position_embeddings": 16384,
        },
        scale_factor=2,
        image_token_id=tokenizer.convert_tokens_to_ids("<image>"),
        pad_token_id=tokenizer.pad_token_id,
    )
    torch.manual_seed(seed)
    model = Idefics3ForConditionalGeneration(config)
    model.generation_config.eos_token_id = tokenizer.eos_token_id
    model.generation_config.pad_token_id = tokenizer.pad_token_id
    model.save_pretrained(folder)
    processor.save_pretrained(folder)
    return folder


def _tokenizer(texts: Iterable[str], vocab: int) -> Any:  # noqa: ANN401 - a fast tokenizer
    from tokenizers import Tokenizer, decoders, models, pre_tokenizers, trainers
    from transformers import PreTrainedTokenizerFast

    bpe = Tokenizer(models.BPE())
    bpe.pre_tokenizer = pre_tokenizers.ByteLevel(add_prefix_space=False)
    bpe.decoder = decoders.ByteLevel()
    trainer = trainers.BpeTrainer(
        vocab_size=vocab,
        special_tokens=SPECIAL,
        initial_alphabet=pre_tokenizers.ByteLevel.alphabet(),
        show_progress=False,
    )
    bpe.train_from_iterator(texts, trainer)
    return PreTrainedTokenizerFast(
        tokenizer_object=bpe,
        pad_token="<pad>",
        eos_token="<end_of_utterance>",
        bos_token="<end_of_utterance>",
        extra_special_tokens={
            "fake_image_token": "<fake_token_around_image>",
            "image_token": "<image>",
            "end_of_utterance_token": "<end_of_utterance>",
            "global_image_token": "<global-img>",
        },
    )
