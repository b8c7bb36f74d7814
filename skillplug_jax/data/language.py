"""Task instructions as word ids: the smallest honest language input, trained from scratch.

No pretrained language model can be downloaded here, so a policy reads an instruction as its
words, each a learned embedding (the model's `instruction_vocab` rows), pooled (act.py). The
vocabulary is every word of the instructions of the installed benchmark's suites (LIBERO's five:
79 words), lower-cased, split at anything but letters and digits, in sorted order after two
reserved ids: PAD (no word) and UNK (a word the vocabulary does not have). A run keeps the
vocabulary it trained with (in its statistics, `VOCABULARY_KEY`), so an instruction reads the same
at evaluation whatever is installed then.

What an unseen word does: it reads as UNK, one embedding shared by every unseen word. No training
instruction holds an unknown word, so UNK's embedding is never trained: an unseen word adds the
same untrained vector to the pool, whatever the word, and an instruction of unseen words only is
the same input as any other such instruction. A word in the vocabulary but in no training
instruction (a suite the policy was not trained on) is in the same position: its embedding
stays at its initialisation.
"""

from __future__ import annotations

import re
from typing import Sequence

import numpy as np

PAD, UNK = 0, 1
RESERVED = ("<pad>", "<unk>")
VOCABULARY_KEY = "instruction_vocabulary"  # where a run's statistics keep its vocabulary


def words(text: str) -> list[str]:
  return re.findall(r"[a-z0-9]+", text.lower())


def vocabulary(instructions: Sequence[str]) -> tuple[str, ...]:
  """Every id's word: the reserved ones, then the instructions' words, sorted."""
  return RESERVED + tuple(sorted({w for text in instructions for w in words(text)}))


def benchmark_vocabulary() -> tuple[str, ...]:
  """The vocabulary of every instruction of LIBERO's installed suites."""
  from envs.libero import suites
  return vocabulary([t.language for s in suites.SUITES for t in suites.tasks(s)])


def encode(instructions: Sequence[str], vocab: Sequence[str], width: int) -> np.ndarray:
  """[N, width] int32 word ids, PAD after the last word; an instruction longer than `width`
  words is an error (cut, it would read as another instruction)."""
  index = {w: i for i, w in enumerate(vocab)}
  if vocab[:len(RESERVED)] != RESERVED:
    raise ValueError(f"a vocabulary starts with {RESERVED}; got {tuple(vocab[:2])}")
  out = np.full((len(instructions), width), PAD, np.int32)
  for i, text in enumerate(instructions):
    ids = [index.get(w, UNK) for w in words(text)]
    if len(ids) > width:
      raise ValueError(f"the instruction {text!r} has {len(ids)} words; the model reads at most {width} "
                       "(model.instruction_words)")
    out[i, :len(ids)] = ids
  return out
