"""Safety evaluation of the merged air picture: conflict prediction with accuracy-aware
thresholds, alert scoring and accuracy-versus-capacity (monograph chapter 5)."""
