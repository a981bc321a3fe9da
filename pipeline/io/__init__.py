"""Readers and writers: rotations text files, ``.mat`` layouts, camera references."""
