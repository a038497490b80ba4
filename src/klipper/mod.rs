//! PURE: Klipper config files (parse, follow includes, edit one value in place, the SAVE_CONFIG
//! block) and G-code command text built from typed values. No I/O beyond what callers pass in.
