//! The Moonraker client: protocol types, the websocket actor, the cloneable handle, HTTP files.
