"""smdinspect.acquire."""
