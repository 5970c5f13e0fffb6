"""The vocabulary every stage shares: the error hierarchy (`errors`), poses named by frames and
the UR pose convention (`geometry`), the cell's named transforms (`frames`), input files read
within limits (`inputs`), files written whole (`files`), strict JSON (`jsonio`), numbers as a
person reads them (`numbers`) and long work's progress (`progress`: bars on a terminal, a few
lines elsewhere).

Layer 1 of `cell`: imports nothing of `cell`, `kernels` or `sim`."""
