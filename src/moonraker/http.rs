//! Moonraker's HTTP side: file upload and download under its roots (`gcodes`, `config`).
//! It sends `X-Api-Key` when one is configured. It must not touch the websocket.

use reqwest::multipart::{Form, Part};
use serde_json::Value;
use sha2::{Digest, Sha256};

use super::Error;

/// HTTP client for Moonraker's file manager.
#[derive(Debug, Clone)]
pub struct Files {
    base: String,
    api_key: Option<String>,
    client: reqwest::Client,
}

impl Files {
    /// `base` is `http://host:port`.
    ///
    /// # Errors
    /// When the HTTP client cannot be built (TLS backend failure).
    pub fn new(
        base: &str,
        api_key: Option<String>,
        timeout: std::time::Duration,
    ) -> Result<Self, Error> {
        let client = reqwest::Client::builder()
            .timeout(timeout)
            .build()
            .map_err(|e| Error::Http {
                method: "-",
                url: base.to_string(),
                message: e.to_string(),
            })?;
        Ok(Self {
            base: base.trim_end_matches('/').to_string(),
            api_key,
            client,
        })
    }

    /// Moonraker's HTTP base, `http://host:port`.
    #[must_use]
    pub(crate) fn base(&self) -> &str {
        &self.base
    }

    fn req(&self, r: reqwest::RequestBuilder) -> reqwest::RequestBuilder {
        match &self.api_key {
            Some(k) => r.header("X-Api-Key", k),
            None => r,
        }
    }

    /// Uploads `bytes` as `root/path` (path may hold folders), with a SHA-256 checksum that
    /// Moonraker verifies. Returns Moonraker's reply.
    ///
    /// # Errors
    /// HTTP failure or Moonraker's refusal (its message included).
    pub async fn upload(&self, root: &str, path: &str, bytes: Vec<u8>) -> Result<Value, Error> {
        let url = format!("{}/server/files/upload", self.base);
        let checksum = hex(&Sha256::digest(&bytes));
        let (dir, name) = match path.rsplit_once('/') {
            Some((d, n)) => (d.to_string(), n.to_string()),
            None => (String::new(), path.to_string()),
        };
        let part = Part::bytes(bytes)
            .file_name(name)
            .mime_str("application/octet-stream")
            .map_err(|e| http_err("POST", &url, e))?;
        let form = Form::new()
            .text("root", root.to_string())
            .text("path", dir)
            .text("checksum", checksum)
            .part("file", part);
        self.result("POST", &url, self.client.post(&url).multipart(form))
            .await
    }

    /// Downloads `root/path`.
    ///
    /// # Errors
    /// HTTP failure, or Moonraker's 404 when the file does not exist.
    pub async fn download(&self, root: &str, path: &str) -> Result<Vec<u8>, Error> {
        let url = format!("{}/server/files/{root}/{path}", self.base);
        self.body("GET", &url, self.client.get(&url)).await
    }

    /// Deletes a file of a root (`DELETE /server/files/{root}/{path}`).
    ///
    /// # Errors
    /// HTTP failure, or Moonraker's refusal (404 when the file does not exist).
    pub(crate) async fn delete(&self, root: &str, path: &str) -> Result<Value, Error> {
        let url = format!("{}/server/files/{root}/{path}", self.base);
        self.result("DELETE", &url, self.client.delete(&url)).await
    }

    /// GET an API path (e.g. `/server/info`) and return the `result` field.
    ///
    /// # Errors
    /// HTTP failure or Moonraker's refusal.
    pub async fn get(&self, path: &str) -> Result<Value, Error> {
        let url = format!("{}{path}", self.base);
        self.result("GET", &url, self.client.get(&url)).await
    }

    /// DELETE an API path (e.g. `/server/webcams/item?uid=…`) and return the `result` field.
    ///
    /// # Errors
    /// HTTP failure or Moonraker's refusal.
    pub(crate) async fn delete_api(&self, path: &str) -> Result<Value, Error> {
        let url = format!("{}{path}", self.base);
        self.result("DELETE", &url, self.client.delete(&url)).await
    }

    /// POST a JSON body to an API path and return the `result` field.
    ///
    /// # Errors
    /// HTTP failure or Moonraker's refusal.
    pub async fn post(&self, path: &str, body: &Value) -> Result<Value, Error> {
        let url = format!("{}{path}", self.base);
        self.result("POST", &url, self.client.post(&url).json(body))
            .await
    }

    /// Sends one request, with the API key, and reads its body whole: every request goes
    /// through here. A status other than success is an error with Moonraker's message.
    async fn body(
        &self,
        method: &'static str,
        url: &str,
        r: reqwest::RequestBuilder,
    ) -> Result<Vec<u8>, Error> {
        let resp = self
            .req(r)
            .send()
            .await
            .map_err(|e| http_err(method, url, e))?;
        let status = resp.status();
        let body = resp.bytes().await.map_err(|e| http_err(method, url, e))?;
        if !status.is_success() {
            return Err(Error::Http {
                method,
                url: url.to_string(),
                message: format!("{status}: {}", moonraker_message(&body)),
            });
        }
        Ok(body.to_vec())
    }

    /// As [`Files::body`], for an API answer: its `result` field (or the whole JSON).
    async fn result(
        &self,
        method: &'static str,
        url: &str,
        r: reqwest::RequestBuilder,
    ) -> Result<Value, Error> {
        let body = self.body(method, url, r).await?;
        let v: Value = serde_json::from_slice(&body).map_err(|e| http_err(method, url, e))?;
        Ok(v.get("result").cloned().unwrap_or(v))
    }
}

fn http_err(method: &'static str, url: &str, e: impl std::fmt::Display) -> Error {
    Error::Http {
        method,
        url: url.to_string(),
        message: e.to_string(),
    }
}

fn moonraker_message(body: &[u8]) -> String {
    serde_json::from_slice::<Value>(body)
        .ok()
        .and_then(|v| v["error"]["message"].as_str().map(str::to_string))
        .unwrap_or_else(|| String::from_utf8_lossy(&body[..body.len().min(300)]).into_owned())
}

fn hex(bytes: &[u8]) -> String {
    use std::fmt::Write;
    bytes.iter().fold(String::new(), |mut s, b| {
        let _ = write!(s, "{b:02x}");
        s
    })
}
