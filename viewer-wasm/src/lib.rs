//! voxstream viewer (in progress).
