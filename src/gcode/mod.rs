//! PURE: the pylon job generator — geometry → toolpaths → G-code text + layout.
//! No I/O: callers read printer facts and write the files.
