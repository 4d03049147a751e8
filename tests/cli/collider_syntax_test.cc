// The command line's collider syntax (client/cli/collider_syntax.h): every kind, and messages that name what
// is wrong.
#include "collider_syntax.h"

#include <gmock/gmock.h>
#include <gtest/gtest.h>

#include "test_util.h"

namespace springblend::cli {
namespace {

using ::testing::HasSubstr;
using springblend::testing::CatchError;

TEST(ColliderSyntax, ReadsEveryKindAndNamesWhatIsWrong) {
  EXPECT_EQ(ParseCollider("sphere:0,0,0,1").shape(), Collider::Shape::kSphere);
  EXPECT_EQ(ParseCollider("capsule:0,0,0,1,0,0,0.5").shape(), Collider::Shape::kCapsule);
  EXPECT_EQ(ParseCollider("box:0,0,0,1,1,1").shape(), Collider::Shape::kBox);
  EXPECT_EQ(ParseCollider("plane:0,0,0,0,1,0").shape(), Collider::Shape::kPlane);
  EXPECT_EQ(ParseCollider("mesh:" + testing::DataPath("spot/spot_low_resolution.obj")).shape(),
            Collider::Shape::kMesh);
  EXPECT_THAT(CatchError([] { ParseCollider("sphere:0,0,1"); }).what(), HasSubstr("takes 4 numbers"));
  EXPECT_THAT(CatchError([] { ParseCollider("sphere:0,0,0,-1"); }).what(), HasSubstr("radius > 0"));
  EXPECT_THAT(CatchError([] { ParseCollider("cone:0,0,0,1"); }).what(), HasSubstr("unknown kind 'cone'"));
  EXPECT_THAT(CatchError([] { ParseCollider("box:0,0,zero,1,1,1"); }).what(), HasSubstr("'zero' is not a number"));
  EXPECT_THAT(CatchError([] { ParseCollider("plane:0,0,0,0,0,0"); }).what(), HasSubstr("non-zero normal"));
  EXPECT_THAT(CatchError([] { ParseCollider("sphere"); }).what(), HasSubstr("expected KIND:VALUES"));
  // An open mesh has no inside.
  EXPECT_THAT(CatchError([] { ParseCollider("mesh:" + testing::DataPath("cylinder/cylinder.obj")); }).what(),
              HasSubstr("must be closed"));
}

TEST(ColliderSyntax, SplitsAMeshSpecIntoItsPath) {
  const ColliderSpec spec = ParseColliderSpec("mesh:a/b:c.obj");
  EXPECT_EQ(spec.kind, "mesh");
  EXPECT_EQ(spec.path, "a/b:c.obj");
  EXPECT_TRUE(spec.values.empty());
}

}  // namespace
}  // namespace springblend::cli
