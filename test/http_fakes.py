"""A loopback HTTP server for the fake KrakenSDR receivers of the tests."""

from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
import threading


class LoopbackHTTP:
    """An HTTP server on 127.0.0.1 that answers every GET with :meth:`respond`.

    ``stop()`` closes the socket (the receiver "dies"); ``start()`` binds the same port again.
    """

    def __init__(self, port=0):
        self.port = port
        self.httpd = None

    def respond(self, handler):
        """Answer one GET on ``handler`` (a BaseHTTPRequestHandler)."""
        raise NotImplementedError

    def start(self):
        fake = self

        class Handler(BaseHTTPRequestHandler):
            def log_message(self, *a):
                pass

            def do_GET(self):   # noqa: N802
                fake.respond(self)

        class Server(ThreadingHTTPServer):
            daemon_threads = True
            allow_reuse_address = True

            def handle_error(self, request, client_address):
                pass     # a client that timed out closed the connection

        self.httpd = Server(('127.0.0.1', self.port), Handler)
        self.port = self.httpd.server_address[1]
        threading.Thread(target=self.httpd.serve_forever, kwargs={'poll_interval': 0.05},
                         daemon=True).start()
        return self

    def stop(self):
        if self.httpd is not None:
            self.httpd.shutdown()
            self.httpd.server_close()
            self.httpd = None
