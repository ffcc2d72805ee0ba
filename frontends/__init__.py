"""Data sources and odometry: a sequence on disk becomes Frames, Frames become poses T_W_S."""
