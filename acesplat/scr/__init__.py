"""Stage 1: scene coordinate regression (encoder + scene-specific head), mapping and localization. Needs torch."""
