//! PURE: layout + readings + printer facts → one solution.
