// The call kinds of the two services, one file each; the handlers in service.cc check the token, parse, and
// hand the call to one of these.
#pragma once

#include <grpcpp/grpcpp.h>
#include <grpcpp/support/byte_buffer.h>

#include "memory_budget.h"
#include "service.h"
#include "springblend/v1/springblend.pb.h"

namespace springblend::server {

// UploadCharacter: the pieces assembled within the request memory budget, then the build (upload_call.cc).
grpc::ServerReadReactor<grpc::ByteBuffer>* NewUploadCall(grpc::CallbackServerContext* call, ServiceContext& context,
                                                         grpc::ByteBuffer* response);
// Solve: a stream of independent frames (solve_call.cc). `received` holds the request's bytes as gRPC received
// them: given back once the parsed request is counted.
grpc::ServerWriteReactor<grpc::ByteBuffer>* NewSolveCall(grpc::CallbackServerContext* call, ServiceContext& context,
                                                         v1::SolveRequest request, Reservation& received);
// Interactive: a session of frames, the newest solved (interactive_call.cc).
grpc::ServerBidiReactor<grpc::ByteBuffer, grpc::ByteBuffer>* NewInteractiveCall(grpc::CallbackServerContext* call,
                                                                               ServiceContext& context);

}  // namespace springblend::server
