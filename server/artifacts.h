#pragma once
// A job's artifacts: the files of its output folder, indexed in the job store when the job ends and streamed
// to clients by FetchArtifacts.
#include <filesystem>
#include <vector>

#include <grpcpp/grpcpp.h>
#include "gaps/v1/trainer.grpc.pb.h"
#include "server/job_store.h"

namespace gaps {

// Every regular file under `out_dir`, relative to it and sorted, so that the index is the same whichever
// replica ends the job.
std::vector<JobStore::Artifact> list_artifacts(const std::filesystem::path& out_dir);

// Streams the files in chunks of rpc::kChunkBytes, each file's last chunk marked. DATA_LOSS when an indexed
// file is gone from disk; CANCELLED when the reader went away.
grpc::Status stream_artifacts(const std::filesystem::path& out_dir, const std::vector<JobStore::Artifact>& artifacts,
                              grpc::ServerWriter<v1::ArtifactChunk>* writer);

}  // namespace gaps
