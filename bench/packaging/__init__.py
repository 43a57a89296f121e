"""What packaging costs and buys: rate, distortion and codec time per ladder point, codecs, the auto ladder, keyframe
rungs."""
