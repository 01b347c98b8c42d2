"""What a training step sees: letterboxed samples, class-balanced sampling, the loader."""
