"""Evaluation: comparing renders with the synthetic ground truth (the only code that reads ``truth/``)."""
