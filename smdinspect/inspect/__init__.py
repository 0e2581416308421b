"""smdinspect.inspect."""
