//! Persistence of calibration sessions and readings in an embedded SQLite database under the
//! data directory. A session is stored as a JSON document with its state beside it, written
//! before each step acts; readings are rows of their own, saved the moment they arrive; a small
//! key/value table keeps what outlives sessions (the backlash camera point). It knows nothing of
//! what a state means: the calibrations tell it which states are final.

use std::path::Path;
use std::sync::Mutex;

use rusqlite::{params, Connection, OptionalExtension};
use serde_json::Value;

/// A storage error.
#[derive(Debug, thiserror::Error)]
pub enum Error {
    /// SQLite failed.
    #[error("session database: {0}")]
    Sql(#[from] rusqlite::Error),
    /// A stored document is not valid JSON (the file was edited or damaged).
    #[error("session database: stored session {id} is damaged: {message}")]
    Damaged {
        /// Session id.
        id: i64,
        /// The JSON error.
        message: String,
    },
    /// The folder for the database cannot be created.
    #[error("cannot create the data folder {path}: {source}")]
    Folder {
        /// The folder.
        path: String,
        /// The I/O error.
        source: std::io::Error,
    },
}

/// One stored session.
#[derive(Debug, Clone, PartialEq)]
pub struct SessionRow {
    /// Id.
    pub id: i64,
    /// Kind, e.g. `ab`.
    pub kind: String,
    /// State name.
    pub state: String,
    /// The whole document.
    pub doc: Value,
}

/// A session in a list: no document.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub(crate) struct SessionSummary {
    /// Id.
    pub id: i64,
    /// Kind, e.g. `ab`.
    pub kind: String,
    /// State name.
    pub state: String,
    /// Created, UTC.
    pub created_at: String,
    /// Last changed, UTC.
    pub updated_at: String,
}

/// One caliper reading.
#[derive(Debug, Clone, PartialEq)]
pub(crate) struct ReadingRow {
    /// Row id.
    pub id: i64,
    /// Round number (1-based).
    pub round: i64,
    /// Pair id, e.g. `A-D1`.
    pub pair: String,
    /// Millimetres.
    pub value_mm: f64,
}

/// The database.
#[derive(Debug)]
pub struct Store {
    conn: Mutex<Connection>,
    /// State names after which a session no longer runs, as the calibrations declare them
    /// (`jobs::core::envelope::SessionState`).
    finals: std::sync::RwLock<std::collections::BTreeSet<String>>,
}

const SCHEMA: &str = "
CREATE TABLE IF NOT EXISTS sessions (
    id INTEGER PRIMARY KEY AUTOINCREMENT,
    kind TEXT NOT NULL,
    state TEXT NOT NULL,
    doc TEXT NOT NULL,
    created_at TEXT NOT NULL DEFAULT (datetime('now')),
    updated_at TEXT NOT NULL DEFAULT (datetime('now'))
);
CREATE TABLE IF NOT EXISTS readings (
    id INTEGER PRIMARY KEY AUTOINCREMENT,
    session_id INTEGER NOT NULL REFERENCES sessions(id),
    round INTEGER NOT NULL,
    pair TEXT NOT NULL,
    value_mm REAL NOT NULL,
    entered_at TEXT NOT NULL DEFAULT (datetime('now'))
);
CREATE INDEX IF NOT EXISTS readings_by_session ON readings(session_id, round);
CREATE TABLE IF NOT EXISTS kv (
    key TEXT PRIMARY KEY,
    value TEXT NOT NULL,
    updated_at TEXT NOT NULL DEFAULT (datetime('now'))
);
";

/// Values once stored as fake finished sessions of a kind of their own, now kept in the `kv`
/// table under a key: (kind, key). Opening a database moves the newest such row's document
/// to its key (unless the key holds a value already) and removes those rows.
const SESSIONS_MOVED_TO_KV: &[(&str, &str)] = &[("backlash_point", "backlash_point")];

impl Store {
    /// Opens (creating when needed) `dir/klipcal.sqlite`.
    ///
    /// # Errors
    /// The folder cannot be created or SQLite cannot open the file.
    pub(crate) fn open(dir: &Path) -> Result<Self, Error> {
        std::fs::create_dir_all(dir).map_err(|source| Error::Folder {
            path: dir.display().to_string(),
            source,
        })?;
        let conn = Connection::open(dir.join("klipcal.sqlite"))?;
        conn.pragma_update(None, "journal_mode", "WAL")?;
        conn.pragma_update(None, "synchronous", "FULL")?;
        Self::init(conn)
    }

    /// An in-memory database, for tests.
    ///
    /// # Errors
    /// SQLite failure.
    #[cfg(test)]
    pub(crate) fn in_memory() -> Result<Self, Error> {
        Self::init(Connection::open_in_memory()?)
    }

    fn init(mut conn: Connection) -> Result<Self, Error> {
        conn.execute_batch(SCHEMA)?;
        let tx = conn.transaction()?;
        for (kind, key) in SESSIONS_MOVED_TO_KV {
            tx.execute(
                "INSERT OR IGNORE INTO kv (key, value, updated_at) \
                 SELECT ?2, doc, updated_at FROM sessions WHERE kind = ?1 ORDER BY id DESC LIMIT 1",
                params![kind, key],
            )?;
            tx.execute("DELETE FROM sessions WHERE kind = ?1", params![kind])?;
        }
        tx.commit()?;
        Ok(Self {
            conn: Mutex::new(conn),
            finals: std::sync::RwLock::new(std::collections::BTreeSet::new()),
        })
    }

    /// Adds state names after which a session no longer runs (each calibration's final
    /// states, registered as the daemon builds them).
    pub(crate) fn add_final_states(&self, names: impl IntoIterator<Item = String>) {
        if let Ok(mut f) = self.finals.write() {
            f.extend(names);
        }
    }

    fn conn(&self) -> std::sync::MutexGuard<'_, Connection> {
        self.conn
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner)
    }

    /// Stores a new session; returns its id.
    ///
    /// # Errors
    /// SQLite failure.
    pub(crate) fn create_session(
        &self,
        kind: &str,
        state: &str,
        doc: &Value,
    ) -> Result<i64, Error> {
        let c = self.conn();
        c.execute(
            "INSERT INTO sessions (kind, state, doc) VALUES (?1, ?2, ?3)",
            params![kind, state, doc.to_string()],
        )?;
        Ok(c.last_insert_rowid())
    }

    /// Replaces a session's state and document.
    ///
    /// # Errors
    /// SQLite failure.
    pub(crate) fn save_session(&self, id: i64, state: &str, doc: &Value) -> Result<(), Error> {
        self.conn().execute(
            "UPDATE sessions SET state = ?2, doc = ?3, updated_at = datetime('now') WHERE id = ?1",
            params![id, state, doc.to_string()],
        )?;
        Ok(())
    }

    fn row(id: i64, kind: String, state: String, doc: String) -> Result<SessionRow, Error> {
        let doc = serde_json::from_str(&doc).map_err(|e| Error::Damaged {
            id,
            message: e.to_string(),
        })?;
        Ok(SessionRow {
            id,
            kind,
            state,
            doc,
        })
    }

    /// One session.
    ///
    /// # Errors
    /// SQLite failure or a damaged document.
    pub(crate) fn session(&self, id: i64) -> Result<Option<SessionRow>, Error> {
        let r = self
            .conn()
            .query_row(
                "SELECT id, kind, state, doc FROM sessions WHERE id = ?1",
                params![id],
                |r| Ok((r.get(0)?, r.get(1)?, r.get(2)?, r.get(3)?)),
            )
            .optional()?;
        r.map(|(id, k, s, d)| Self::row(id, k, s, d)).transpose()
    }

    /// The newest session that has not reached a final state.
    ///
    /// # Errors
    /// SQLite failure or a damaged document.
    pub(crate) fn active_session(&self) -> Result<Option<SessionRow>, Error> {
        let placeholders = self
            .finals
            .read()
            .map(|f| {
                f.iter()
                    .map(|s| format!("'{}'", s.replace('\'', "''")))
                    .collect::<Vec<_>>()
                    .join(",")
            })
            .unwrap_or_default();
        let sql = format!(
            "SELECT id, kind, state, doc FROM sessions WHERE state NOT IN ({placeholders}) \
             ORDER BY id DESC LIMIT 1"
        );
        let r = self
            .conn()
            .query_row(&sql, [], |r| {
                Ok((r.get(0)?, r.get(1)?, r.get(2)?, r.get(3)?))
            })
            .optional()?;
        r.map(|(id, k, s, d)| Self::row(id, k, s, d)).transpose()
    }

    /// The newest session of any state.
    ///
    /// # Errors
    /// SQLite failure or a damaged document.
    pub(crate) fn latest_session(&self) -> Result<Option<SessionRow>, Error> {
        let r = self
            .conn()
            .query_row(
                "SELECT id, kind, state, doc FROM sessions ORDER BY id DESC LIMIT 1",
                [],
                |r| Ok((r.get(0)?, r.get(1)?, r.get(2)?, r.get(3)?)),
            )
            .optional()?;
        r.map(|(id, k, s, d)| Self::row(id, k, s, d)).transpose()
    }

    /// The newest sessions first, at most `limit`: id, kind, state and when each was created
    /// and last changed (UTC, `YYYY-MM-DD HH:MM:SS`), without their documents.
    ///
    /// # Errors
    /// SQLite failure.
    pub(crate) fn sessions(&self, limit: usize) -> Result<Vec<SessionSummary>, Error> {
        let conn = self.conn();
        let mut st = conn.prepare(
            "SELECT id, kind, state, created_at, updated_at FROM sessions ORDER BY id DESC LIMIT ?1",
        )?;
        let rows = st.query_map(params![limit as i64], |r| {
            Ok(SessionSummary {
                id: r.get(0)?,
                kind: r.get(1)?,
                state: r.get(2)?,
                created_at: r.get(3)?,
                updated_at: r.get(4)?,
            })
        })?;
        Ok(rows.collect::<Result<Vec<_>, _>>()?)
    }

    /// The newest session of one kind, in any state.
    ///
    /// # Errors
    /// SQLite failure or a damaged document.
    pub(crate) fn latest_session_of(&self, kind: &str) -> Result<Option<SessionRow>, Error> {
        let r = self
            .conn()
            .query_row(
                "SELECT id, kind, state, doc FROM sessions WHERE kind = ?1 ORDER BY id DESC LIMIT 1",
                params![kind],
                |r| Ok((r.get(0)?, r.get(1)?, r.get(2)?, r.get(3)?)),
            )
            .optional()?;
        r.map(|(id, k, s, d)| Self::row(id, k, s, d)).transpose()
    }

    /// The newest session of one kind in one state.
    ///
    /// # Errors
    /// SQLite failure or a damaged document.
    pub(crate) fn latest_session_of_in(
        &self,
        kind: &str,
        state: &str,
    ) -> Result<Option<SessionRow>, Error> {
        let r = self
            .conn()
            .query_row(
                "SELECT id, kind, state, doc FROM sessions WHERE kind = ?1 AND state = ?2 \
                 ORDER BY id DESC LIMIT 1",
                params![kind, state],
                |r| Ok((r.get(0)?, r.get(1)?, r.get(2)?, r.get(3)?)),
            )
            .optional()?;
        r.map(|(id, k, s, d)| Self::row(id, k, s, d)).transpose()
    }

    /// Stores `value` under `key` (replacing what was there): a setting klipcal keeps between
    /// sessions, such as the backlash camera point.
    ///
    /// # Errors
    /// SQLite failure.
    pub fn set_value(&self, key: &str, value: &Value) -> Result<(), Error> {
        self.conn().execute(
            "INSERT INTO kv (key, value) VALUES (?1, ?2) \
             ON CONFLICT(key) DO UPDATE SET value = ?2, updated_at = datetime('now')",
            params![key, value.to_string()],
        )?;
        Ok(())
    }

    /// The value stored under `key`, if any.
    ///
    /// # Errors
    /// SQLite failure or a damaged value.
    pub(crate) fn value(&self, key: &str) -> Result<Option<Value>, Error> {
        let v: Option<String> = self
            .conn()
            .query_row("SELECT value FROM kv WHERE key = ?1", params![key], |r| {
                r.get(0)
            })
            .optional()?;
        v.map(|text| {
            serde_json::from_str(&text).map_err(|e| Error::Damaged {
                id: 0,
                message: format!("value {key}: {e}"),
            })
        })
        .transpose()
    }

    /// Saves one reading; returns its row id.
    ///
    /// # Errors
    /// SQLite failure.
    #[cfg(test)]
    pub(crate) fn add_reading(
        &self,
        session: i64,
        round: i64,
        pair: &str,
        value_mm: f64,
    ) -> Result<i64, Error> {
        let c = self.conn();
        c.execute(
            "INSERT INTO readings (session_id, round, pair, value_mm) VALUES (?1, ?2, ?3, ?4)",
            params![session, round, pair, value_mm],
        )?;
        Ok(c.last_insert_rowid())
    }

    /// Saves one entry's readings in one transaction: all of them or none.
    ///
    /// # Errors
    /// SQLite failure (then nothing of the entry is saved).
    pub(crate) fn add_readings(
        &self,
        session: i64,
        round: i64,
        pair: &str,
        values_mm: &[f64],
    ) -> Result<(), Error> {
        let mut c = self.conn();
        let tx = c.transaction()?;
        for v in values_mm {
            tx.execute(
                "INSERT INTO readings (session_id, round, pair, value_mm) VALUES (?1, ?2, ?3, ?4)",
                params![session, round, pair, v],
            )?;
        }
        tx.commit()?;
        Ok(())
    }

    /// Removes a pair's readings of one round (to enter them again); returns how many.
    ///
    /// # Errors
    /// SQLite failure.
    pub(crate) fn clear_readings(
        &self,
        session: i64,
        round: i64,
        pair: &str,
    ) -> Result<usize, Error> {
        Ok(self.conn().execute(
            "DELETE FROM readings WHERE session_id = ?1 AND round = ?2 AND pair = ?3",
            params![session, round, pair],
        )?)
    }

    /// Every reading of a session's round, in the order entered.
    ///
    /// # Errors
    /// SQLite failure.
    pub(crate) fn readings(&self, session: i64, round: i64) -> Result<Vec<ReadingRow>, Error> {
        let c = self.conn();
        let mut st = c.prepare(
            "SELECT id, round, pair, value_mm FROM readings \
             WHERE session_id = ?1 AND round = ?2 ORDER BY id",
        )?;
        let rows = st
            .query_map(params![session, round], |r| {
                Ok(ReadingRow {
                    id: r.get(0)?,
                    round: r.get(1)?,
                    pair: r.get(2)?,
                    value_mm: r.get(3)?,
                })
            })?
            .collect::<Result<Vec<_>, _>>()?;
        Ok(rows)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use serde_json::json;

    #[test]
    fn a_session_and_its_readings_survive_reopening_the_database() {
        let dir = tempfile::tempdir().unwrap();
        let id = {
            let s = Store::open(dir.path()).unwrap();
            s.add_final_states(["cancelled".to_string()]);
            let id = s
                .create_session("ab", "preflight", &json!({"round": 1}))
                .unwrap();
            s.save_session(id, "measuring", &json!({"round": 1, "x": 2}))
                .unwrap();
            s.add_reading(id, 1, "A-D1", 10.02).unwrap();
            s.add_reading(id, 1, "A-D1", 10.03).unwrap();
            id
        };
        let s = Store::open(dir.path()).unwrap();
        s.add_final_states(["cancelled".to_string()]);
        let row = s.active_session().unwrap().unwrap();
        assert_eq!((row.id, row.state.as_str()), (id, "measuring"));
        assert_eq!(row.doc["x"], 2);
        let r = s.readings(id, 1).unwrap();
        assert_eq!(
            r.iter().map(|r| r.value_mm).collect::<Vec<_>>(),
            vec![10.02, 10.03]
        );
    }

    #[test]
    fn a_finished_session_is_not_active() {
        let s = Store::in_memory().unwrap();
        s.add_final_states(["cancelled".to_string()]);
        let id = s.create_session("ab", "preflight", &json!({})).unwrap();
        s.save_session(id, "cancelled", &json!({})).unwrap();
        assert!(s.active_session().unwrap().is_none());
        assert_eq!(s.latest_session().unwrap().unwrap().state, "cancelled");
    }

    #[test]
    fn a_value_is_kept_under_its_key_and_replaced_whole() {
        let s = Store::in_memory().unwrap();
        assert_eq!(s.value("backlash_point").unwrap(), None);
        s.set_value("backlash_point", &json!({"point": [1.0, 2.0, 3.0]}))
            .unwrap();
        s.set_value("backlash_point", &json!({"point": [4.0, 5.0, 6.0]}))
            .unwrap();
        assert_eq!(
            s.value("backlash_point").unwrap(),
            Some(json!({"point": [4.0, 5.0, 6.0]}))
        );
        assert!(s.sessions(10).unwrap().is_empty(), "a value is no session");
    }

    #[test]
    fn a_camera_point_saved_as_a_fake_session_moves_to_its_key_on_opening() {
        let dir = tempfile::tempdir().unwrap();
        {
            // How klipcal up to 0.x saved it: a finished session of kind backlash_point, one
            // per SET_POINT, beside a real session.
            let s = Store::open(dir.path()).unwrap();
            for p in [[1.0, 2.0, 3.0], [7.5, 8.5, 9.5]] {
                s.create_session(
                    "backlash_point",
                    "done",
                    &json!({"point": p, "state": "done"}),
                )
                .unwrap();
            }
            s.create_session("ab", "measuring", &json!({"x": 1}))
                .unwrap();
        }
        let s = Store::open(dir.path()).unwrap();
        assert_eq!(
            s.value("backlash_point").unwrap().unwrap()["point"],
            json!([7.5, 8.5, 9.5]),
            "the newest point is kept"
        );
        let kinds: Vec<String> = s
            .sessions(10)
            .unwrap()
            .into_iter()
            .map(|r| r.kind)
            .collect();
        assert_eq!(kinds, vec!["ab"]);
        // Opening again changes nothing; a point saved since is not overwritten.
        s.set_value("backlash_point", &json!({"point": [0.0, 0.0, 0.0]}))
            .unwrap();
        drop(s);
        let s = Store::open(dir.path()).unwrap();
        assert_eq!(
            s.value("backlash_point").unwrap().unwrap()["point"],
            json!([0.0, 0.0, 0.0])
        );
    }

    #[test]
    fn clearing_a_pair_keeps_the_other_pairs() {
        let s = Store::in_memory().unwrap();
        let id = s.create_session("ab", "measuring", &json!({})).unwrap();
        s.add_reading(id, 1, "A-D1", 10.0).unwrap();
        s.add_reading(id, 1, "A-D2", 150.0).unwrap();
        assert_eq!(s.clear_readings(id, 1, "A-D1").unwrap(), 1);
        let r = s.readings(id, 1).unwrap();
        assert_eq!(r.len(), 1);
        assert_eq!(r[0].pair, "A-D2");
    }
}
