"""The package's exceptions."""


class RpcError(Exception):
    """A call the server refused or could not answer.

    ``code`` is the gRPC status code as a number (3 for INVALID_ARGUMENT), ``code_name`` its
    name, ``details`` the server's message.
    """

    def __init__(self, code, code_name, details):
        super().__init__(f"{code_name}: {details}")
        self.code = code
        self.code_name = code_name
        self.details = details


class JobFailed(Exception):
    """A job that ended failed or cancelled; ``job`` is its last state (``job.error`` says why)."""

    def __init__(self, job):
        super().__init__(f"job {job.id} {job.state}: {job.error or 'no reason given'}")
        self.job = job
