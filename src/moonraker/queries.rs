//! The typed queries on the [`Moonraker`] handle: G-code, `server.info`/`printer.info`, printer
//! objects, print start, firmware restart, and the answers jobs read typed (configfile,
//! bed_mesh, heaters, webcams; see [`super::answers`]).

use std::time::Duration;

use serde_json::{json, Map, Value};

use super::answers::{
    BedMeshStatus, ConfigFile, HeaterStatus, PrinterInfo, ServerInfo, WebcamList,
};
use super::{Error, Moonraker};

impl Moonraker {
    /// Runs a G-code script and waits until Klipper has executed it.
    ///
    /// # Errors
    /// Klipper's error (e.g. `Must home axis first`) as [`Error::Rpc`]. An unknown command is
    /// not an error here: Klipper reports it on the console as `// Unknown command`.
    pub async fn gcode(&self, script: &str) -> Result<(), Error> {
        self.call("printer.gcode.script", json!({ "script": script }))
            .await
            .map(|_| ())
    }

    /// [`Moonraker::gcode`] with its own time limit.
    ///
    /// # Errors
    /// As [`Moonraker::gcode`].
    pub async fn gcode_within(&self, script: &str, limit: Duration) -> Result<(), Error> {
        self.call_within("printer.gcode.script", json!({ "script": script }), limit)
            .await
            .map(|_| ())
    }

    /// `server.info`.
    ///
    /// # Errors
    /// As [`Moonraker::call`].
    pub(crate) async fn server_info(&self) -> Result<ServerInfo, Error> {
        ServerInfo::parse(self.call("server.info", Value::Null).await?)
    }

    /// `printer.info`.
    ///
    /// # Errors
    /// As [`Moonraker::call`].
    pub async fn printer_info(&self) -> Result<PrinterInfo, Error> {
        PrinterInfo::parse(self.call("printer.info", Value::Null).await?)
    }

    /// `printer.objects.list`: the names of every printer object.
    ///
    /// # Errors
    /// As [`Moonraker::call`].
    pub(crate) async fn objects_list(&self) -> Result<Vec<String>, Error> {
        let v = self.call("printer.objects.list", Value::Null).await?;
        Ok(v["objects"]
            .as_array()
            .map(|a| {
                a.iter()
                    .filter_map(|s| s.as_str().map(str::to_string))
                    .collect()
            })
            .unwrap_or_default())
    }

    /// `printer.objects.query`: object name → fields (null for all). Returns object → status.
    ///
    /// # Errors
    /// As [`Moonraker::call`].
    pub async fn objects_query(&self, objects: Value) -> Result<Map<String, Value>, Error> {
        let v = self
            .call("printer.objects.query", json!({ "objects": objects }))
            .await?;
        match v.get("status") {
            Some(Value::Object(m)) => Ok(m.clone()),
            _ => Err(Error::Protocol(format!("query reply without status: {v}"))),
        }
    }

    /// `printer.print.start` for a file under the `gcodes` root.
    ///
    /// # Errors
    /// As [`Moonraker::call`]; Moonraker refuses while a print runs.
    pub async fn print_start(&self, filename: &str) -> Result<(), Error> {
        self.call("printer.print.start", json!({ "filename": filename }))
            .await
            .map(|_| ())
    }

    /// `printer.firmware_restart`.
    ///
    /// # Errors
    /// As [`Moonraker::call`].
    pub async fn firmware_restart(&self) -> Result<(), Error> {
        self.call("printer.firmware_restart", Value::Null)
            .await
            .map(|_| ())
    }

    /// Klipper's configfile object, typed: `config` (text as written) and the `settings` klipcal
    /// reads (parsed, with Klipper's defaults).
    ///
    /// # Errors
    /// As [`Moonraker::call`]; [`Error::Protocol`] when the answer is malformed.
    pub async fn configfile(&self) -> Result<ConfigFile, Error> {
        let mut m = self
            .objects_query(json!({ "configfile": ["config", "settings"] }))
            .await?;
        ConfigFile::parse(m.remove("configfile").unwrap_or_else(|| json!({})))
    }

    /// Klipper's `bed_mesh` status, typed: the `fields` asked for (`profile_name`,
    /// `probed_matrix`, `profiles`).
    ///
    /// # Errors
    /// As [`Moonraker::call`]; [`Error::Protocol`] when the answer is malformed.
    pub async fn bed_mesh(&self, fields: &[&str]) -> Result<BedMeshStatus, Error> {
        let mut m = self.objects_query(json!({ "bed_mesh": fields })).await?;
        BedMeshStatus::parse(m.remove("bed_mesh").unwrap_or_else(|| json!({})))
    }

    /// A heater's or temperature sensor's status, typed: the `fields` asked for (`temperature`,
    /// `target`, `power`); all `None` when Klipper has no object `name`.
    ///
    /// # Errors
    /// As [`Moonraker::call`]; [`Error::Protocol`] when the answer is malformed.
    pub(crate) async fn heater(&self, name: &str, fields: &[&str]) -> Result<HeaterStatus, Error> {
        let mut m = self.objects_query(json!({ name: fields })).await?;
        HeaterStatus::parse(name, m.remove(name).unwrap_or_else(|| json!({})))
    }

    /// Moonraker's webcams (`server.webcams.list`), typed.
    ///
    /// # Errors
    /// As [`Moonraker::call`]; [`Error::Protocol`] when the answer is malformed.
    pub(crate) async fn webcams(&self) -> Result<WebcamList, Error> {
        WebcamList::parse(self.call("server.webcams.list", json!({})).await?)
    }
}
