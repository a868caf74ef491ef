"""Training: data (sampled shapes, noise variants, patch batches), losses, the two-stage loop."""
