"""The encoder and its heads: what the model is."""
