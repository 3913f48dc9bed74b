"""codesign_mb."""
