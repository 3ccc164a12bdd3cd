"""Open-ended terms: generic parametric forms for physics the canonical library lacks.

placeholder, filled in by the lead (issue 20)."""
