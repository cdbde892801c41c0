"""The simulated lab: strobe controller with fault injection, synthetic cameras, subjects, boards, charts."""
