//! The printer summary shown by `check` and `klipcal_status`, built from Moonraker's answers.
