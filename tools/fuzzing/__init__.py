"""Fuzzing guard's decoders and core (`tools/fuzz.py`, `tests/unit/test_fuzz_*.py`).

- `contract`: what every sample a source emits promises (finite, SI units, in physical range), and
  what the core's events promise (finite estimates); a broken promise is a `Broken` error.
- `seeds`: tiny valid inputs of every format, built by hand (struct) or with pymavlink and dronecan:
  the seed corpus, and what the property tests mutate.
- `targets`: one function per target, bytes in, the decoder run and its output checked; only the
  errors a target documents may come out of it.
"""
