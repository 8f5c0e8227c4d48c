// Example: one EPOS4 (node-ID 1) in Profile Position Mode, driven from C++.
//
// Run it after `roslaunch maxon_epos4_ros_canopen
// maxon_epos4_canopen_motor_1dof_ppm.launch` (sim:=true for the virtual
// EPOS4). A text menu calls the driver services (init, halt, recover,
// shutdown), publishes a target position on the position controller's command
// topic and prints the position read from /maxon/joint_states.

#include <ros/ros.h>
#include <sensor_msgs/JointState.h>
#include <std_msgs/Float64.h>
#include <std_srvs/Trigger.h>

#include <cmath>
#include <iostream>
#include <limits>
#include <mutex>
#include <string>

namespace
{
const std::string kNamespace = "/maxon";
const std::string kJoint = "base_link1_joint";

class PositionReader
{
public:
  explicit PositionReader(ros::NodeHandle& nh)
    : sub_(nh.subscribe(kNamespace + "/joint_states", 1, &PositionReader::onJointStates, this))
  {
  }

  // Latest position of kJoint; false when none arrived yet.
  bool get(double& position, double& velocity)
  {
    std::lock_guard<std::mutex> lock(mutex_);
    position = position_;
    velocity = velocity_;
    return received_;
  }

private:
  void onJointStates(const sensor_msgs::JointState::ConstPtr& msg)
  {
    for (size_t i = 0; i < msg->name.size(); ++i)
    {
      if (msg->name[i] != kJoint)
        continue;
      std::lock_guard<std::mutex> lock(mutex_);
      position_ = i < msg->position.size() ? msg->position[i] : 0.0;
      velocity_ = i < msg->velocity.size() ? msg->velocity[i] : 0.0;
      received_ = true;
    }
  }

  ros::Subscriber sub_;
  std::mutex mutex_;
  double position_ = 0.0;
  double velocity_ = 0.0;
  bool received_ = false;
};

void callTrigger(ros::NodeHandle& nh, const std::string& name)
{
  const std::string service = kNamespace + "/driver/" + name;
  ros::ServiceClient client = nh.serviceClient<std_srvs::Trigger>(service);
  if (!client.waitForExistence(ros::Duration(5.0)))
  {
    ROS_ERROR("%s is not available: is the launch file running?", service.c_str());
    return;
  }
  std_srvs::Trigger trigger;
  if (client.call(trigger))
    ROS_INFO("%s: success=%s %s", service.c_str(), trigger.response.success ? "true" : "false",
             trigger.response.message.c_str());
  else
    ROS_ERROR("calling %s failed", service.c_str());
}

void printMenu()
{
  ROS_INFO("*************");
  ROS_INFO("maxon EPOS4 - ROS 1 example code (maxon_epos4_ros_canopen)");
  ROS_INFO("To be used with 1 EPOS4 with Node-ID 1, after roslaunch of a PPM example");
  ROS_INFO("MENU");
  ROS_INFO("1 - driver init");
  ROS_INFO("2 - driver halt");
  ROS_INFO("3 - driver recover");
  ROS_INFO("4 - driver shutdown");
  ROS_INFO("5 - set Target Position");
  ROS_INFO("6 - get Position Actual Value");
  ROS_INFO("7 - Exit");
  ROS_INFO("Please enter a menu choice:");
}

// Waits until done() holds, at most `seconds` (the spinner thread serves callbacks meanwhile).
template <typename Predicate>
void waitUpTo(double seconds, Predicate done)
{
  const ros::WallTime deadline = ros::WallTime::now() + ros::WallDuration(seconds);
  while (!done() && ros::ok() && ros::WallTime::now() < deadline)
    ros::WallDuration(0.05).sleep();
}

// Reads a number from stdin; false on end of input.
template <typename T>
bool readValue(T& value)
{
  while (!(std::cin >> value))
  {
    if (std::cin.eof())
      return false;
    std::cin.clear();
    std::cin.ignore(std::numeric_limits<std::streamsize>::max(), '\n');
    ROS_WARN("please enter a number");
  }
  return true;
}
}  // namespace

int main(int argc, char** argv)
{
  ros::init(argc, argv, "cpp_example_1dof_ppm");
  ros::NodeHandle nh;
  ros::AsyncSpinner spinner(1);  // serves the joint_states subscriber while we wait for input
  spinner.start();

  PositionReader reader(nh);
  ros::Publisher command = nh.advertise<std_msgs::Float64>(
      kNamespace + "/canopen_motor/base_link1_joint_position_controller/command", 1, true);

  while (ros::ok())
  {
    printMenu();
    int choice = 0;
    if (!readValue(choice))
      break;
    switch (choice)
    {
      case 1:
        callTrigger(nh, "init");
        break;
      case 2:
        callTrigger(nh, "halt");
        break;
      case 3:
        callTrigger(nh, "recover");
        break;
      case 4:
        callTrigger(nh, "shutdown");
        break;
      case 5:
      {
        ROS_INFO("Target Position [inc]:");
        double target = 0.0;
        if (!readValue(target))
          return 0;
        if (!std::isfinite(target))
        {
          ROS_WARN("the target must be a finite number");
          break;
        }
        // The controller subscribes to the topic; give the connection a
        // moment to form when this is the first command after start-up.
        waitUpTo(2.0, [&command] { return command.getNumSubscribers() > 0; });
        std_msgs::Float64 msg;
        msg.data = target;
        command.publish(msg);
        ROS_INFO("Target Position %.0f sent", target);
        break;
      }
      case 6:
      {
        double position = 0.0, velocity = 0.0;
        // Right after start-up the first joint_states may still be on its way.
        waitUpTo(2.0, [&] { return reader.get(position, velocity); });
        if (reader.get(position, velocity))
          ROS_INFO("Position Actual Value: %.0f inc (velocity %.0f rpm)", position, velocity);
        else
          ROS_WARN("no joint_states received yet: is the joint_state_controller running (after init)?");
        break;
      }
      case 7:
        ros::shutdown();
        return 0;
      default:
        ROS_WARN("unknown choice %d", choice);
    }
  }
  return 0;
}
