//! The one parse at the boundary: a remote method or an HTTP path finds its [`Route`] (one
//! lookup in a map built once from the command tables), and the route reads the arguments into
//! one typed [`Call`], which `jobs::registry` matches on. The remote methods registered with
//! Moonraker, the API's paths (with the tables' aliases) and every generated artifact read the
//! same list ([`all_ops`]).

use std::collections::HashMap;
use std::sync::LazyLock;

use serde_json::Value;

use super::ab::AbCall;
use super::backlash::BacklashCall;
use super::core::table::{self, Args, Op, OpSpec};
use super::core::{CoreCall, CORE_OPS};
use super::mesh::MeshCall;

/// Every operation's call, typed at the boundary: one variant per table, each with one
/// variant per operation and its typed arguments.
#[derive(Debug, Clone, PartialEq)]
pub(crate) enum Call {
    /// The operations every daemon answers ([`CORE_OPS`]).
    Core(CoreCall),
    /// The A/B calibration's.
    Ab(AbCall),
    /// The backlash measurement's.
    Backlash(BacklashCall),
    /// The thermal mesh's.
    Mesh(MeshCall),
}

/// Which table an operation is in, and where.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Owner {
    Core(usize),
    Ab(usize),
    Backlash(usize),
    Mesh(usize),
}

/// Where a call goes: its operation's declaration, the flag an HTTP alias sets, and the parse
/// of its table.
#[derive(Debug, Clone, Copy, PartialEq)]
pub(crate) struct Route {
    /// The operation.
    pub spec: &'static OpSpec,
    /// The flag an alias path sets (`ab/clear`: `clear`).
    pub sets: Option<&'static str>,
    owner: Owner,
}

impl Route {
    /// The route of a remote method.
    #[must_use]
    pub(crate) fn of_method(method: &str) -> Option<Self> {
        ROUTES.by_method.get(method).copied()
    }

    /// The route of the operation the agent answers itself (`klipcal_status`).
    #[must_use]
    pub(crate) fn status() -> Self {
        ROUTES.status
    }

    /// The route of an HTTP path under `/api/` (an alias's too).
    #[must_use]
    pub(crate) fn of_path(path: &str) -> Option<Self> {
        ROUTES.by_path.get(path).copied()
    }

    /// Reads `args` into the typed call: the one boundary between a caller's JSON and the
    /// handlers.
    ///
    /// # Errors
    /// An unknown or twice-given argument, or a bad value, each named.
    pub(crate) fn parse(&self, args: &Value) -> anyhow::Result<Call> {
        let a = Args::parse(args, self.spec)?;
        match self.owner {
            Owner::Core(i) => (CORE_OPS[i].parse)(&a).map(Call::Core),
            Owner::Ab(i) => (super::ab::OPS[i].parse)(&a).map(Call::Ab),
            Owner::Backlash(i) => (super::backlash::OPS[i].parse)(&a).map(Call::Backlash),
            Owner::Mesh(i) => (super::mesh::OPS[i].parse)(&a).map(Call::Mesh),
        }
    }
}

struct Routes {
    status: Route,
    all: Vec<&'static OpSpec>,
    methods: Vec<String>,
    by_method: HashMap<&'static str, Route>,
    by_path: HashMap<&'static str, Route>,
}

static ROUTES: LazyLock<Routes> = LazyLock::new(|| {
    fn add<C>(list: &mut Vec<Route>, ops: &'static [Op<C>], owner: fn(usize) -> Owner) {
        list.extend(ops.iter().enumerate().map(|(i, o)| Route {
            spec: &o.spec,
            sets: None,
            owner: owner(i),
        }));
    }
    let mut list = Vec::new();
    add(&mut list, CORE_OPS, Owner::Core);
    add(&mut list, super::ab::OPS, Owner::Ab);
    add(&mut list, super::backlash::OPS, Owner::Backlash);
    add(&mut list, super::mesh::OPS, Owner::Mesh);
    let mut by_method = HashMap::new();
    let mut by_path = HashMap::new();
    for r in &list {
        if let Some(m) = r.spec.method {
            by_method.insert(m, *r);
        }
        if let Some(p) = r.spec.http {
            by_path.insert(p, *r);
        }
        if let Some(a) = r.spec.alias {
            by_path.insert(
                a.http,
                Route {
                    sets: Some(a.sets),
                    ..*r
                },
            );
        }
    }
    Routes {
        status: *list
            .iter()
            .find(|r| r.spec.by_agent)
            .expect("the core table declares the status"),
        all: list.iter().map(|r| r.spec).collect(),
        methods: list
            .iter()
            .filter_map(|r| r.spec.method.map(str::to_string))
            .collect(),
        by_method,
        by_path,
    }
});

/// Every operation klipcal has, in the order a user meets them: the common ones, then each
/// calibration's.
#[must_use]
pub fn all_ops() -> &'static [&'static OpSpec] {
    &ROUTES.all
}

/// Every remote method the daemon registers with Moonraker.
#[must_use]
pub(crate) fn all_methods() -> &'static [String] {
    &ROUTES.methods
}

/// Every path a POST may name under `/api/`: each operation's, then the aliases.
#[must_use]
pub(crate) fn operation_paths() -> Vec<&'static str> {
    all_ops()
        .iter()
        .filter_map(|o| o.http)
        .chain(all_ops().iter().filter_map(|o| o.alias.map(|a| a.http)))
        .collect()
}

/// `config/klipcal.cfg`, generated from the table (`klipcal macros`).
#[must_use]
pub(crate) fn macros_cfg() -> String {
    table::macros_cfg(all_ops())
}

#[cfg(test)]
mod tests {
    use super::*;
    use serde_json::json;

    #[test]
    fn a_method_and_its_path_reach_the_same_operation_and_an_alias_sets_its_flag() {
        for op in all_ops() {
            if let (Some(m), Some(p)) = (op.method, op.http) {
                assert_eq!(Route::of_method(m).unwrap().spec, *op);
                assert_eq!(Route::of_path(p).unwrap().spec, *op);
            }
        }
        let clear = Route::of_path("ab/clear").unwrap();
        assert_eq!(clear.spec.method, Some("klipcal_measure"));
        assert_eq!(clear.sets, Some("clear"));
        assert!(Route::of_method("klipcal_nope").is_none());
        let status = Route::of_method("klipcal_status").unwrap();
        assert!(status.spec.by_agent);
        assert_eq!(
            status.parse(&json!({})).unwrap(),
            Call::Core(CoreCall::Status)
        );
    }
}
