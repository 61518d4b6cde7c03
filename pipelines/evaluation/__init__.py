"""What a trained run is scored by: metrics, paper-style tables, the report, refinement at test time, figures."""
