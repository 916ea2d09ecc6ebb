"""parq_train: generated-scene training of small PARQ models (torch; never used at run time)."""
