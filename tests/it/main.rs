//! Integration tests: one binary. Each test starts its own bench (a real Moonraker and a real
//! klippy on loopback, see tests/bench/) and, where needed, the `klipcal` daemon, on free
//! ports in its own folder, and stops them when done.

mod backlash;
mod backlash_camera;
mod backlash_image;
mod backlash_job;
mod bench;
mod browser;
mod cli;
mod daemon;
mod docs;
mod fake;
mod faults;
mod frontends;
mod hosts;
mod http;
mod install;
mod mainsail;
mod mesh;
mod mesh_job;
mod ops;
mod outage;
mod page_phone;
mod pylons;
mod readings;
mod realcfg;
mod runall;
mod session;
mod skew;
mod soak_ask;
mod startup;
mod try_bench;
