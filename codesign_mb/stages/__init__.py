"""Training of the stages A-D (``sec_pipeline``), for the learned and the model-based stacks."""
