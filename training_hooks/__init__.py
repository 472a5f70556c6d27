"""Dataloader and training-loop integration for torchface (normalised faces inside PyTorch pipelines)."""
