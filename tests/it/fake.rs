//! Faults the real Moonraker cannot produce on demand, from an in-process websocket server:
//! a reply that never comes, and a connection dropped mid-request.

use std::time::Duration;

use futures_util::{SinkExt, StreamExt};
use klipcal::moonraker::{ClientOptions, Error, Moonraker};
use serde_json::{json, Map, Value};
use tokio::net::TcpListener;
use tokio_tungstenite::tungstenite::Message;
use tokio_util::sync::CancellationToken;

/// A fake Moonraker: answers identify/server.info, and treats `hang` (never answers) and
/// `drop` (closes the socket) as faults. Counts connections.
async fn fake_server() -> (String, tokio::sync::mpsc::UnboundedReceiver<()>) {
    let listener = TcpListener::bind("127.0.0.1:0").await.unwrap();
    let url = format!("ws://{}/websocket", listener.local_addr().unwrap());
    let (tx, rx) = tokio::sync::mpsc::unbounded_channel();
    tokio::spawn(async move {
        while let Ok((tcp, _)) = listener.accept().await {
            let tx = tx.clone();
            tokio::spawn(async move {
                let mut ws = tokio_tungstenite::accept_async(tcp).await.unwrap();
                let _ = tx.send(());
                while let Some(Ok(Message::Text(t))) = ws.next().await {
                    let v: Value = serde_json::from_str(&t).unwrap();
                    let id = v["id"].clone();
                    let result = match v["method"].as_str().unwrap_or("") {
                        "server.connection.identify" => json!({"connection_id": 1}),
                        "server.info" => json!({"klippy_state": "startup"}),
                        "hang" => continue,
                        "drop" => return,
                        _ => json!("ok"),
                    };
                    let reply = json!({"jsonrpc": "2.0", "id": id, "result": result});
                    if ws
                        .send(Message::Text(reply.to_string().into()))
                        .await
                        .is_err()
                    {
                        return;
                    }
                }
            });
        }
    });
    (url, rx)
}

fn options(url: String) -> ClientOptions {
    ClientOptions {
        url,
        api_key: None,
        client_name: "klipcal-test".into(),
        agent: false,
        request_timeout: Duration::from_millis(500),
        reconnect_min: Duration::from_millis(50),
        reconnect_max: Duration::from_millis(200),
        remote_methods: vec![],
        subscriptions: Map::new(),
    }
}

#[tokio::test]
async fn a_reply_that_never_comes_times_out_and_the_connection_keeps_working() {
    let (url, _conns) = fake_server().await;
    let cancel = CancellationToken::new();
    let (m, _) = Moonraker::spawn(options(url), cancel.clone());
    m.wait_connected(Duration::from_secs(5)).await.unwrap();
    let err = m.call("hang", Value::Null).await.unwrap_err();
    assert!(matches!(err, Error::Timeout { .. }), "{err}");
    assert!(err.to_string().contains("hang"), "{err}");
    assert_eq!(m.call("other", Value::Null).await.unwrap(), json!("ok"));
    cancel.cancel();
}

#[tokio::test]
async fn a_dropped_connection_fails_the_waiting_request_and_reconnects() {
    let (url, mut conns) = fake_server().await;
    let cancel = CancellationToken::new();
    let (m, _) = Moonraker::spawn(options(url), cancel.clone());
    m.wait_connected(Duration::from_secs(5)).await.unwrap();
    conns.recv().await.unwrap();
    let err = m.call("drop", Value::Null).await.unwrap_err();
    assert!(matches!(err, Error::Disconnected(_)), "{err}");
    // It reconnects by itself and works again.
    tokio::time::timeout(Duration::from_secs(5), conns.recv())
        .await
        .unwrap()
        .unwrap();
    m.wait_connected(Duration::from_secs(5)).await.unwrap();
    assert_eq!(m.call("other", Value::Null).await.unwrap(), json!("ok"));
    cancel.cancel();
}

#[tokio::test]
async fn shutdown_stops_the_actor_and_fails_new_requests() {
    let (url, _conns) = fake_server().await;
    let cancel = CancellationToken::new();
    let (m, _) = Moonraker::spawn(options(url), cancel.clone());
    m.wait_connected(Duration::from_secs(5)).await.unwrap();
    cancel.cancel();
    let mut st = m.state_watch();
    tokio::time::timeout(
        Duration::from_secs(2),
        st.wait_for(|s| *s == klipcal::moonraker::ConnState::Stopped),
    )
    .await
    .unwrap()
    .unwrap();
    assert!(m.call("other", Value::Null).await.is_err());
}
