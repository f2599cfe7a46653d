"""Pre-training, zero-shot, fine-tuning and evaluation loops."""
