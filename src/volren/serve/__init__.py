"""`volren serve`: live multi-viewer rendering over WebSockets (docs/SERVE.md). One render loop renders every
connected viewer's newest camera in one multi-view call and streams each its JPEG frame."""
