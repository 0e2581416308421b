"""smdinspect.synth."""
