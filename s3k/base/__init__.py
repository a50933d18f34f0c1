"""The house's foundations, imported by every room and importing none: user errors (`errors`), atomic file
writes and the lock (`fileio`), where a command may write (`outputs`), how the library speaks (`messages`),
numeric ranges (`ranges`), the fixed choices as `Literal` types (`choices`), drawing keypoints (`draw`), the
metrics (`metrics`) and, without 3D truth, the labels as the reference (`label_reference`)."""
