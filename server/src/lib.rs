//! voxstream server library (filled in by the build pipeline work).
