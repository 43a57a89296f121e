"""Whether playback holds the frame rate: real-time runs, their logs and timelines, the player's knobs."""
