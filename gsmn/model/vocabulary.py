"""The instruction vocabulary (paper: Instruction and Image Embedding; original code: text handling).

Words are tokenised as the original (punctuation to spaces, lower case, whitespace split) and mapped to ids;
id 0 pads, id 1 stands for any unknown word. The word list is every word an instruction can contain
(`gsmn.task.instructions.VOCABULARY`); checkpoints store it so a model always reads the ids it was trained on.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from functools import cached_property

from gsmn.task.instructions import VOCABULARY, tokenize

PAD = "<pad>"
UNK = "<unk>"


@dataclass(frozen=True)
class Vocabulary:
    words: tuple[str, ...]  # id i is words[i]; words[0] = PAD, words[1] = UNK

    def __post_init__(self) -> None:
        if self.words[:2] != (PAD, UNK):
            raise ValueError(f"a vocabulary starts with {PAD!r}, {UNK!r}; got {self.words[:2]}")
        if len(set(self.words)) != len(self.words):
            raise ValueError("vocabulary words must be unique")

    @classmethod
    def default(cls) -> Vocabulary:
        return cls((PAD, UNK, *VOCABULARY))

    @property
    def pad_id(self) -> int:
        return 0

    @property
    def unk_id(self) -> int:
        return 1

    def __len__(self) -> int:
        return len(self.words)

    def encode(self, text: str) -> list[int]:
        """Token ids of `text`; unknown words map to UNK. Never empty: an empty text encodes as [UNK]."""
        index = self._index
        ids = [index.get(w, self.unk_id) for w in tokenize(text)]
        return ids or [self.unk_id]

    def decode(self, ids: list[int]) -> list[str]:
        return [self.words[i] for i in ids if i != self.pad_id]

    @cached_property
    def _index(self) -> dict[str, int]:
        return {w: i for i, w in enumerate(self.words)}

    def to_json(self) -> str:
        return json.dumps({"words": list(self.words)}, indent=1)

    @classmethod
    def from_json(cls, text: str) -> Vocabulary:
        d = json.loads(text)
        if not isinstance(d, dict) or not isinstance(d.get("words"), list) \
                or not all(isinstance(w, str) for w in d["words"]):
            raise ValueError('a vocabulary file holds {"words": [str, ...]}')
        return cls(tuple(d["words"]))
