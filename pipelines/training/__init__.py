"""What a run is asked to do and how it learns: config, variants, objective, losses, data, the run folder."""
