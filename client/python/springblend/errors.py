"""The one exception type of the springblend Python client."""

import grpc


class SpringblendError(Exception):
    """A call failed: carries the gRPC status code and the server's message, which names the field at fault.

    Attributes:
        code: a grpc.StatusCode (INVALID_ARGUMENT for bad data, NOT_FOUND for an unknown character,
            RESOURCE_EXHAUSTED when the server is full, UNAVAILABLE when it cannot be reached, ...).
        message: the server's (or this client's) explanation, meant for a person.
    """

    def __init__(self, code, message):
        super().__init__(f"{code.name}: {message}")
        self.code = code
        self.message = message

    @classmethod
    def from_rpc_error(cls, error):
        """Converts a grpc.RpcError raised by a stub into a SpringblendError."""
        code = error.code() if hasattr(error, "code") else grpc.StatusCode.UNKNOWN
        details = error.details() if hasattr(error, "details") else str(error)
        return cls(code or grpc.StatusCode.UNKNOWN, details or "no message from the server")


def invalid_argument(message):
    """A SpringblendError for a mistake this client catches before anything is sent."""
    return SpringblendError(grpc.StatusCode.INVALID_ARGUMENT, message)


def bad_answer(message):
    """A SpringblendError (DATA_LOSS) for an answer from the server this client will not trust: frames missing,
    extra, repeated or out of order, arrays of the wrong shape, positions that are not finite."""
    return SpringblendError(grpc.StatusCode.DATA_LOSS, f"the server's answer is not a solution: {message}")
